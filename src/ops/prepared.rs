//! A convolution's weights as a backend prepared them for inference, kept by the module that
//! owns the weights (the grid model's U-Net blocks, `model/grid/unet.rs`) and handed to
//! [`super::NetOps::conv3x3_forward`]. The CPU's Winograd kernel (`cpu/winograd.rs`) keeps
//! its transformed kernel `U = G g G^T` here: inference (`eval`, `node`, `bench node`) runs
//! the same weights step after step, and transforming them every step wrote as many bytes as
//! the products read.
//!
//! One entry per slot, keyed by the identity of the weight tensor it was prepared from (the
//! backend keeps a handle on that tensor beside the prepared values and compares buffers):
//! new weights replace the entry, so a slot holds at most one prepared copy and one handle
//! on the weights. A clone of the owning module starts with an empty slot of its own.

use std::any::Any;
use std::sync::{Arc, Mutex};

/// What a slot holds: the backend's handle on the weights, and what it prepared from them.
type Entry = (Box<dyn Any + Send>, Arc<Vec<f32>>);

/// One convolution's prepared weights (see the module doc); empty until the first
/// inference step on a backend that prepares weights.
#[derive(Default)]
pub struct PreparedWeights {
    slot: Mutex<Option<Entry>>,
}

impl PreparedWeights {
    /// The prepared values kept for a weight `K` for which `same` holds; otherwise
    /// `prepare` runs and, when it returns `(key, values)`, they replace the entry. None
    /// when nothing was kept for such a weight and `prepare` returns None.
    pub fn get_or_prepare<K: Any + Send>(
        &self,
        same: impl Fn(&K) -> bool,
        prepare: impl FnOnce() -> Option<(K, Vec<f32>)>,
    ) -> Option<Arc<Vec<f32>>> {
        let mut slot = self.slot.lock().unwrap_or_else(|e| e.into_inner());
        if let Some((key, values)) = slot.as_ref() {
            if key.downcast_ref::<K>().is_some_and(&same) {
                return Some(Arc::clone(values));
            }
        }
        let (key, values) = prepare()?;
        let values = Arc::new(values);
        *slot = Some((Box::new(key), Arc::clone(&values)));
        Some(values)
    }
}

impl Clone for PreparedWeights {
    /// An empty slot: a copy of a module prepares its own weights (it may be given others).
    fn clone(&self) -> Self {
        Self::default()
    }
}

impl std::fmt::Debug for PreparedWeights {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        let kept = self.slot.lock().map(|s| s.is_some()).unwrap_or_default();
        f.debug_struct("PreparedWeights")
            .field("kept", &kept)
            .finish()
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn one_entry_replaced_when_the_key_changes() {
        let slot = PreparedWeights::default();
        let mut runs = 0;
        let mut get = |key: u32| {
            slot.get_or_prepare(
                |k: &u32| *k == key,
                || {
                    runs += 1;
                    Some((key, vec![key as f32]))
                },
            )
        };
        assert_eq!(*get(1).unwrap(), vec![1.0]);
        assert_eq!(*get(1).unwrap(), vec![1.0]);
        assert_eq!(*get(2).unwrap(), vec![2.0]);
        assert_eq!(*get(1).unwrap(), vec![1.0]);
        assert_eq!(runs, 3, "1 prepared, reused, replaced by 2, prepared again");
        let copy = slot.clone();
        assert!(format!("{copy:?}").contains("kept: false"));
    }
}
