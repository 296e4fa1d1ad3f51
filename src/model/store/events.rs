//! The rebound part's contacts of a device call's scenes ([`SlotEvents`]): taken from the
//! scenes' constraint data (the host's [`SceneShape`]s, in the slots the states share) as the
//! flat tables the device reads, and given back into them after the call (read when the scene
//! next projects), so a scene's contacts carry on from call to call wherever its next call
//! projects, device or host.

use std::sync::{Arc, Mutex};

use crate::model::constraints::SceneShape;
use crate::ops::{event_table_len, EventStore, Events, TablesLater};

/// One trajectory's constraint data, shared by the states that carry it (clones of a state
/// share it too; `ConstraintState::detached` copies it); empty until its first projection.
pub(super) type Slot = Arc<Mutex<Option<SceneShape>>>;

/// The slots of a call's scenes, in call order, with `r` bodies a table row (the call's
/// most, `ProjectionPlan::rebound`).
pub(super) struct SlotEvents {
    slots: Vec<Slot>,
    r: usize,
}

impl SlotEvents {
    /// The plan's store for scenes `slots` and `r` bodies a row; none where `r` is 0.
    pub(super) fn events(slots: &[Slot], r: usize) -> Events {
        let store = Self {
            slots: slots.to_vec(),
            r,
        };
        Events((r > 0).then(|| Arc::new(store) as Arc<dyn EventStore>))
    }
}

impl EventStore for SlotEvents {
    fn take(&self) -> Vec<f32> {
        let per = event_table_len(self.r);
        let mut out = vec![0.0; per * self.slots.len()];
        for (slot, table) in self.slots.iter().zip(out.chunks_exact_mut(per)) {
            let mut shape = slot.lock().unwrap_or_else(|e| e.into_inner());
            if let Some(shape) = shape.as_mut() {
                shape.write_events(self.r, table);
            }
        }
        out
    }

    fn give_back(&self, tables: TablesLater) {
        for (at, slot) in self.slots.iter().enumerate() {
            let mut shape = slot.lock().unwrap_or_else(|e| e.into_inner());
            if let Some(shape) = shape.as_mut() {
                shape.defer_events(tables.clone(), self.r, at);
            }
        }
    }
}
