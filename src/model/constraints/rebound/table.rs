//! A scene's rebound contacts as the flat table a device reads and writes
//! (`crate::ops::ProjectionPlan::events`): per body `a` a row of `r + 4` contacts, the pair
//! with body `b > a` at column `b` and the wall `side` at column `r + side`, each
//! [`EVENT_VALUES`] values (1 while in progress, the approach speed or -1 where unknown, the
//! frames it has been leaving). The table is the same map [`Rebound::apply`] keeps, so a call
//! on the device and one on the host carry the same contacts on.

use super::{Event, Rebound, WALL};
use crate::ops::{event_table_len, TablesLater, EVENT_VALUES};

/// The contacts a device call left, not read yet: the call's tables, their bodies a row and
/// this scene's index in the call.
#[derive(Clone)]
pub(in crate::model::constraints) struct Pending {
    tables: TablesLater,
    r: usize,
    at: usize,
}

impl std::fmt::Debug for Pending {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("Pending")
            .field("r", &self.r)
            .field("at", &self.at)
            .finish()
    }
}

impl Rebound {
    /// The number of bodies.
    pub(in crate::model::constraints) fn body_count(&self) -> usize {
        self.bodies.len()
    }

    /// The particles of body `b` (increasing indices).
    pub(in crate::model::constraints) fn body(&self, b: usize) -> &[u32] {
        self.bodies.of(b)
    }

    /// Keeps the contacts a device call left (scene `at` of its `tables`, `r` bodies a row)
    /// to be read when they are next used ([`Rebound::settle`]).
    pub(in crate::model::constraints) fn defer(
        &mut self,
        tables: TablesLater,
        r: usize,
        at: usize,
    ) {
        self.pending = Some(Pending { tables, r, at });
    }

    /// Reads the contacts a device call left, if any (waiting for the call): where the read
    /// failed, the contacts stay as they were before it.
    pub(in crate::model::constraints) fn settle(&mut self) {
        if let Some(p) = self.pending.take() {
            let per = event_table_len(p.r);
            let tables = (p.tables)();
            if let Some(table) = tables.get(p.at * per..(p.at + 1) * per) {
                self.read_table(p.r, table);
            }
        }
    }

    /// Writes the contacts in progress into `out` (`[r (r + 4) EVENT_VALUES]`, zeroed by
    /// the caller) for a call whose scenes have at most `r` bodies (this scene's at most
    /// `r`).
    pub(in crate::model::constraints) fn write_table(&mut self, r: usize, out: &mut [f32]) {
        self.settle();
        for (&(a, other), event) in &self.events {
            let at = slot(r, a, other);
            out[at] = 1.0;
            out[at + 1] = event.speed_in.unwrap_or(-1.0);
            out[at + 2] = event.leaving as f32;
        }
    }

    /// Replaces the contacts in progress by those of `table` (layout of
    /// [`Rebound::write_table`]).
    pub(in crate::model::constraints) fn read_table(&mut self, r: usize, table: &[f32]) {
        self.pending = None;
        self.events.clear();
        let n = self.bodies.len() as u32;
        for a in 0..n {
            let others = (a + 1..n).chain((0..4).map(|side| WALL + side));
            for other in others {
                let at = slot(r, a, other);
                if table[at] == 1.0 {
                    let speed = table[at + 1];
                    let event = Event {
                        speed_in: (speed >= 0.0).then_some(speed),
                        leaving: table[at + 2] as u32,
                    };
                    self.events.insert((a, other), event);
                }
            }
        }
    }
}

/// Where contact `(a, other)` starts in a table of `r` bodies a row.
fn slot(r: usize, a: u32, other: u32) -> usize {
    let column = match other >= WALL {
        true => r + (other - WALL) as usize,
        false => other as usize,
    };
    (a as usize * (r + 4) + column) * EVENT_VALUES
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn a_table_round_trip_keeps_every_contact() {
        let bodies = vec![vec![0u32, 1, 2], vec![3, 4, 5], vec![6, 7, 8]];
        let mut rebound = Rebound::new(&bodies, 9).unwrap();
        let events = [
            ((0, 2), Some(1.5), 0),
            ((1, WALL + 2), None, 3),
            ((2, WALL + 3), Some(0.0), 1),
        ];
        for (key, speed_in, leaving) in events {
            rebound.events.insert(key, Event { speed_in, leaving });
        }
        // Room for four bodies a row, as in a call whose largest scene has four.
        let mut table = vec![0.0; 4 * 8 * EVENT_VALUES];
        rebound.write_table(4, &mut table);
        assert_eq!(table.iter().filter(|&&v| v == 1.0).count(), 3 + 1);
        let mut back = Rebound::new(&bodies, 9).unwrap();
        back.read_table(4, &table);
        let seen: Vec<_> = (back.events.iter())
            .map(|(&k, e)| (k, e.speed_in, e.leaving))
            .collect();
        assert_eq!(seen, events);
        // Deferred: read when next used, the scene's own table of the call's.
        let mut later = Rebound::new(&bodies, 9).unwrap();
        let two: std::sync::Arc<[f32]> = [vec![0.0; table.len()], table].concat().into();
        later.defer(std::sync::Arc::new(move || two.clone()), 4, 1);
        assert!(later.events.is_empty());
        later.settle();
        assert_eq!(later.events.len(), 3);
    }
}
