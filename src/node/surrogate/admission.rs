//! The surrogate node's admission rules, as pure functions of one frame and what the node
//! knows of its scene: [`check_frame`] says whether a decoded frame may be predicted on at
//! all (particle count, material ids, finite values, the message's own checks);
//! [`admission`] says what a frame does to its scene's hidden state (start again, go on,
//! reset over a gap, drop an older frame, ignore a scene already rolled out). The first is
//! applied by the decoder thread (`intake.rs`), the second by `scenes.rs`; used
//! by `minflow node`.

use crate::msgs::ParticleFrame;

use super::options::OnGap;

/// Why the node rejects a decoded frame (counted and logged; the node keeps serving).
#[derive(Debug, Clone, PartialEq, thiserror::Error)]
pub(super) enum Rejection {
    /// The model takes a fixed particle count (the paper's architecture) and this is another.
    #[error("{got} particles, the model was trained for N = {model}")]
    ParticleCount { got: usize, model: usize },
    /// A material id outside [`crate::material::TABLE`].
    #[error("unknown material id {0} ({known})", known = crate::material::id_list())]
    Material(u8),
    /// A NaN or infinity in the state.
    #[error("non-finite position, velocity or dt")]
    NonFinite,
    /// The message's own checks ([`ParticleFrame::validate`]).
    #[error("{0}")]
    Invalid(String),
}

/// Reasons a frame is rejected, checked in order; `model_n` is the model's fixed particle
/// count, None where it takes any.
pub(super) fn check_frame(frame: &ParticleFrame, model_n: Option<usize>) -> Result<(), Rejection> {
    if let Some(model) = model_n.filter(|&n| n != frame.len()) {
        return Err(Rejection::ParticleCount {
            got: frame.len(),
            model,
        });
    }
    // Branch-free passes the compiler vectorises; a search only on failure (on one local
    // core a frame of 2,500 particles took 10-12 us to check with early-exit searches, and
    // about 1.1 us so, `validate` included).
    if let Some((_, m)) = crate::material::Material::first_unknown(&frame.material) {
        return Err(Rejection::Material(m));
    }
    let finite = |v: &[f32]| v.iter().fold(true, |ok, x| ok & x.is_finite());
    if !finite(&frame.position) || !finite(&frame.velocity) || !frame.dt.is_finite() {
        return Err(Rejection::NonFinite);
    }
    frame
        .validate()
        .map_err(|e| Rejection::Invalid(e.to_string()))
}

/// What a frame does to its scene's hidden state.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub(super) enum Admission {
    /// The scene starts (frame 0, unseen scene, idle past the timeout): a fresh state.
    Restart,
    /// The frame follows the last one (or [`OnGap::Skip`] over a forward gap): step on.
    Continue,
    /// A gap or an out-of-order frame under [`OnGap::Reset`]: the hidden state starts
    /// again, the stream's reference positions are kept.
    GapReset,
    /// An older frame under [`OnGap::Skip`]: not predicted on, counted as dropped.
    DropOlder,
    /// Closed loop, the scene was already rolled out (even if its state was since dropped
    /// as idle or evicted) and this is not its frame 0: not predicted on, not counted.
    Ignore,
}

/// What the scene knows when a frame arrives.
#[derive(Debug, Clone, Copy)]
pub(super) struct SceneView {
    /// Frame index of the last frame admitted, None for an unseen scene.
    pub last_index: Option<u32>,
    /// No frame for longer than the idle timeout.
    pub idle_too_long: bool,
    /// Closed loop: the scene's rollout was started (remembered beyond its state).
    pub rolled_out: bool,
}

/// The state rule for frame `index` of a scene in `view` (module doc of [`super`]);
/// `closed_loop` is true when the node runs with `--rollout`.
pub(super) fn admission(
    view: SceneView,
    index: u32,
    closed_loop: bool,
    on_gap: OnGap,
) -> Admission {
    // Closed loop: one rollout per scene, however long the scene was idle or forgotten;
    // only its start again (frame 0, a replay looping) rolls it out again.
    if closed_loop && view.rolled_out && index != 0 {
        return Admission::Ignore;
    }
    let restart = index == 0 || view.last_index.is_none() || view.idle_too_long;
    if restart {
        return Admission::Restart;
    }
    let follows = view
        .last_index
        .is_some_and(|last| index == last.wrapping_add(1));
    if follows {
        return Admission::Continue;
    }
    let older = view.last_index.is_some_and(|last| index <= last);
    match on_gap {
        OnGap::Reset => Admission::GapReset,
        OnGap::Skip if older => Admission::DropOlder,
        OnGap::Skip => Admission::Continue,
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn seen(last: u32) -> SceneView {
        SceneView {
            last_index: Some(last),
            idle_too_long: false,
            rolled_out: false,
        }
    }

    #[test]
    fn bad_frames_are_named() {
        let mut f = ParticleFrame {
            position: vec![0.5; 4],
            velocity: vec![0.0; 4],
            material: vec![0, 1],
            dt: 0.016,
            ..ParticleFrame::default()
        };
        assert_eq!(check_frame(&f, Some(2)), Ok(()));
        let wrong_n = check_frame(&f, Some(3)).unwrap_err();
        assert_eq!(wrong_n, Rejection::ParticleCount { got: 2, model: 3 });
        assert!(wrong_n.to_string().contains("N = 3"));
        f.material[1] = 9;
        assert_eq!(check_frame(&f, None), Err(Rejection::Material(9)));
        f.material[1] = 0;
        f.velocity[3] = f32::NAN;
        assert_eq!(check_frame(&f, None), Err(Rejection::NonFinite));
    }

    #[test]
    fn the_state_rules_as_a_table() {
        use Admission::*;
        let unseen = SceneView {
            last_index: None,
            ..seen(0)
        };
        let idle = SceneView {
            idle_too_long: true,
            ..seen(4)
        };
        let rolled = SceneView {
            rolled_out: true,
            ..seen(4)
        };
        // (view, frame index, closed loop, gap policy) -> rule
        let cases = [
            (unseen, 7, false, OnGap::Reset, Restart),
            (seen(4), 0, false, OnGap::Skip, Restart),
            (idle, 9, false, OnGap::Skip, Restart),
            (seen(4), 5, false, OnGap::Reset, Continue),
            (seen(4), 7, false, OnGap::Reset, GapReset),
            (seen(4), 3, false, OnGap::Reset, GapReset),
            (seen(4), 4, false, OnGap::Skip, DropOlder),
            (seen(4), 7, false, OnGap::Skip, Continue),
            (rolled, 5, true, OnGap::Reset, Ignore),
            // Issue 40: a rolled-out scene idle past the timeout or forgotten stays done.
            (
                SceneView {
                    idle_too_long: true,
                    ..rolled
                },
                9,
                true,
                OnGap::Reset,
                Ignore,
            ),
            (
                SceneView {
                    last_index: None,
                    ..rolled
                },
                9,
                true,
                OnGap::Reset,
                Ignore,
            ),
            (rolled, 0, true, OnGap::Reset, Restart),
            (rolled, 5, false, OnGap::Reset, Continue),
        ];
        for (view, index, closed, gap, want) in cases {
            assert_eq!(
                admission(view, index, closed, gap),
                want,
                "{view:?} frame {index}"
            );
        }
    }
}
