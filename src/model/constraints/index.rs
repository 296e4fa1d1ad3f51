//! Which body each particle belongs to, for the parts that move whole bodies (contact,
//! rebound): the bodies' particles one body after another, and the index back from a
//! particle to its body.

/// The particles of a scene's bodies, body by body, and each particle's body.
#[derive(Debug, Clone, Default)]
pub(super) struct BodyIndex {
    /// `[N]`: body index per particle, `u32::MAX` for particles of no body.
    pub(super) body_of: Vec<u32>,
    /// The particles of all bodies, body after body.
    pub(super) ids: Vec<u32>,
    /// `[bodies + 1]`: where each body's particles start in `ids`.
    starts: Vec<usize>,
}

impl BodyIndex {
    /// The index of `bodies` (each its particle indices) in a scene of `n` particles.
    pub(super) fn new<'a>(bodies: impl IntoIterator<Item = &'a [u32]>, n: usize) -> Self {
        let mut body_of = vec![u32::MAX; n];
        let mut ids = Vec::new();
        let mut starts = vec![0];
        for (b, body) in bodies.into_iter().enumerate() {
            for &i in body {
                body_of[i as usize] = b as u32;
            }
            ids.extend_from_slice(body);
            starts.push(ids.len());
        }
        Self {
            body_of,
            ids,
            starts,
        }
    }

    /// The number of bodies.
    pub(super) fn len(&self) -> usize {
        self.starts.len().saturating_sub(1)
    }

    /// The particles of body `b`.
    pub(super) fn of(&self, b: usize) -> &[u32] {
        &self.ids[self.starts[b]..self.starts[b + 1]]
    }

    /// Adds `by[body]` (`[bodies]`) to columns `col, col + 1` of every body particle's row of
    /// `frame` (`[N, 4]`).
    pub(super) fn add(&self, frame: &mut [f32], by: &[[f32; 2]], col: usize) {
        for &i in &self.ids {
            let s = by[self.body_of[i as usize] as usize];
            frame[4 * i as usize + col] += s[0];
            frame[4 * i as usize + col + 1] += s[1];
        }
    }
}
