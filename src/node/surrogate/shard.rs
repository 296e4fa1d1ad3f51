//! Sharding scenes across surrogate nodes over zenoh (`minflow node --shard GROUP`): every
//! node of a group declares a zenoh liveliness token `minflow/shard/<GROUP>/<member>` and
//! follows the group's tokens with a liveliness subscriber (history on: the members alive
//! when it starts, then each join and leave). zenoh withdraws the token of a node that
//! exits or dies (its session's links close, or its lease runs out), so the member set is
//! zenoh's own view of who is alive: there is no coordinator. Each scene belongs to the
//! member with the highest score `hash(member, scene)` (rendezvous or highest-random-weight
//! hashing, Thaler and Ravishankar 1998): every node computes the same owner from the same
//! member set, and when a member leaves only its own scenes move, each to the member with
//! its next highest score. A node predicts only the scenes it owns; one that takes a scene
//! over starts its state again from the next frame (`intake.rs` counts and logs it).
//! Used by `minflow node`.

use std::collections::BTreeSet;
use std::sync::{Arc, Mutex};
use std::time::Duration;

use zenoh::sample::SampleKind;
use zenoh::Wait;

use crate::transport::{TransportError, TransportKind};

/// Key expression prefix of the group tokens.
const PREFIX: &str = "minflow/shard";

/// This node's membership in a shard group, and the members alive now.
pub(super) struct Shard {
    me: String,
    members: Arc<Mutex<BTreeSet<String>>>,
    _token: zenoh::liveliness::LivelinessToken,
    _subscriber: zenoh::pubsub::Subscriber<()>,
}

impl Shard {
    /// Joins `group` on `session` as `name` (made unique with the session's zenoh id).
    ///
    /// # Errors
    /// [`TransportError::Declare`] when the token or the subscriber cannot be declared, or
    /// `group` is not a valid key expression chunk.
    pub(super) fn join(
        session: &zenoh::Session,
        group: &str,
        name: &str,
    ) -> Result<Shard, TransportError> {
        let declare_err = |reason: String| {
            TransportError::declare(
                TransportKind::Zenoh,
                "shard liveliness",
                format!("{PREFIX}/{group}"),
                reason,
            )
        };
        let me = format!(
            "{}-{}",
            name.replace(['/', '*', '$', '?', '#'], "_"),
            session.zid()
        );
        let members = Arc::new(Mutex::new(BTreeSet::from([me.clone()])));
        let seen = Arc::clone(&members);
        let prefix = format!("{PREFIX}/{group}/");
        let (log_name, own, within) = (name.to_owned(), me.clone(), prefix.clone());
        let subscriber = session
            .liveliness()
            .declare_subscriber(format!("{PREFIX}/{group}/*"))
            .history(true)
            .callback(move |sample| {
                let Some(member) = sample.key_expr().as_str().strip_prefix(&within) else {
                    return;
                };
                let mut set = seen.lock().expect("member set poisoned");
                let changed = match sample.kind() {
                    SampleKind::Put => set.insert(member.to_owned()),
                    SampleKind::Delete => member != own && set.remove(member),
                };
                if changed {
                    let how = if sample.kind() == SampleKind::Put {
                        "joined"
                    } else {
                        "left"
                    };
                    tracing::info!(
                        "{log_name}: shard member {member} {how}; {} alive",
                        set.len()
                    );
                }
            })
            .wait()
            .map_err(|e| declare_err(e.to_string()))?;
        let token = session
            .liveliness()
            .declare_token(format!("{PREFIX}/{group}/{me}"))
            .wait()
            .map_err(|e| declare_err(e.to_string()))?;
        // The members alive now, before the first frame is routed (the subscriber's
        // history arrives on zenoh's threads, possibly later).
        let replies = session
            .liveliness()
            .get(format!("{PREFIX}/{group}/*"))
            .timeout(Duration::from_secs(1))
            .wait()
            .map_err(|e| declare_err(e.to_string()))?;
        while let Ok(reply) = replies.recv() {
            let key = reply.result().map(|s| s.key_expr().as_str().to_owned());
            if let Some(member) = key.ok().as_deref().and_then(|k| k.strip_prefix(&prefix)) {
                members
                    .lock()
                    .expect("member set poisoned")
                    .insert(member.to_owned());
            }
        }
        Ok(Shard {
            me,
            members,
            _token: token,
            _subscriber: subscriber,
        })
    }

    /// Who owns each scene as this node sees the group, for another thread (the decoder's).
    pub(super) fn owners(&self) -> Owners {
        Owners {
            me: self.me.clone(),
            members: Arc::clone(&self.members),
        }
    }

    /// Members alive now (this node included).
    pub(super) fn members(&self) -> usize {
        self.members.lock().expect("member set poisoned").len()
    }
}

/// This node's view of who owns each scene, shared with the group's liveliness subscriber.
#[derive(Clone)]
pub(super) struct Owners {
    me: String,
    members: Arc<Mutex<BTreeSet<String>>>,
}

impl Owners {
    /// True when this node owns `scene` among the members alive now.
    pub(super) fn mine(&self, scene: &str) -> bool {
        let members = self.members.lock().expect("member set poisoned");
        owner(members.iter().map(String::as_str), scene) == Some(self.me.as_str())
    }
}

/// The member with the highest rendezvous score for `scene` (ties: the larger name); None
/// without members.
pub fn owner<'a>(members: impl IntoIterator<Item = &'a str>, scene: &str) -> Option<&'a str> {
    members.into_iter().max_by_key(|m| (score(m, scene), *m))
}

/// A stable 64-bit score of (member, scene): FNV-1a over both, separated, then the
/// SplitMix64 finalizer to spread it. The same on every machine and build (unlike std's
/// `DefaultHasher`), so nodes of different builds agree.
fn score(member: &str, scene: &str) -> u64 {
    let mut h: u64 = 0xcbf2_9ce4_8422_2325;
    for b in member.bytes().chain([0xff]).chain(scene.bytes()) {
        h ^= u64::from(b);
        h = h.wrapping_mul(0x0100_0000_01b3);
    }
    h ^= h >> 30;
    h = h.wrapping_mul(0xbf58_476d_1ce4_e5b9);
    h ^= h >> 27;
    h = h.wrapping_mul(0x94d0_49bb_1331_11eb);
    h ^ (h >> 31)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn owners_are_spread_and_only_a_leaving_members_scenes_move() {
        let three = ["a", "b", "c"];
        let scenes: Vec<String> = (0..300).map(|i| format!("multi/{i:03}")).collect();
        let before: Vec<&str> = scenes.iter().map(|s| owner(three, s).unwrap()).collect();
        for m in three {
            let n = before.iter().filter(|o| **o == m).count();
            assert!((60..=140).contains(&n), "{m} owns {n} of 300");
        }
        let after: Vec<&str> = scenes
            .iter()
            .map(|s| owner(["a", "c"], s).unwrap())
            .collect();
        for (b, a) in before.iter().zip(&after) {
            if *b != "b" {
                assert_eq!(b, a, "a scene of a staying member moved");
            }
        }
        assert_eq!(owner([], "x"), None);
    }
}
