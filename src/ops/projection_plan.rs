//! [`ProjectionPlan`]: the projection of one call laid out for a device (plain data; built by
//! `model::constraints::projection_plan`, run by the CUDA backend's
//! [`NetOps::project_constraints`](super::NetOps::project_constraints):
//! `cuda/projection/` the call (`op.rs`, `call.rs`), `liquid*.rs` the liquid and the walls,
//! `cuda/projection/solids.rs` and `cuda/projection/contact.rs` the ropes, the bodies' shape matching and their
//! contact).

/// Materials a plan keeps apart in its moves (`crate::material::COUNT`).
pub const MATERIALS: usize = 4;

/// Values per scene in [`ProjectionPlan::scenes`].
pub const SCENE_VALUES: usize = 10 + MATERIALS;

use std::any::Any;
use std::sync::{Arc, OnceLock};

/// Values at the head of [`ProjectionPlan::solids`].
pub const SOLIDS_HEAD: usize = 20;

/// Values per scene in [`ProjectionPlan::solids`], after its head.
pub const SCENE_SOLIDS: usize = 6;

/// Where the momentum part's values start in the head of [`ProjectionPlan::solids`].
pub const MOMENTUM_AT: usize = 8;

/// Where the rebound part's values start in the head of [`ProjectionPlan::solids`].
pub const REBOUND_AT: usize = 13;

/// Values per contact of [`ProjectionPlan::events`]' tables: 1 while it is in progress, its
/// approach speed (-1 where unknown), the frames it has been leaving.
pub const EVENT_VALUES: usize = 3;

/// Values per body in [`ProjectionPlan::solids`]' body table.
pub const BODY_VALUES: usize = 8;

/// The most shape-matched bodies a scene the device projects may have (its contact pairs are
/// held in the kernel's shared memory); a scene with more projects on the host.
pub const MAX_BODIES: usize = 16;

/// The projection of one call's K predicted frames (`[K B, N, 4]`) on a device.
///
/// Per scene `s` (row `s` of [`ProjectionPlan::scenes`], [`SCENE_VALUES`] each): node spacing
/// `h` (domain units), nodes per side (0: no liquid, the pressure part skipped), the
/// compressed threshold, the band along the walls (width, domain units) and its threshold,
/// the walls `lo` and `hi` (domain units), the time step `dt`, the solids' volume per
/// particle (the liquid's median rest volume, cells), 0 (spare), then the particle spacing of
/// each of the [`MATERIALS`] in the rest frame (domain units; 0 where the scene has none), by
/// which the moves are counted.
#[derive(Clone, Debug, PartialEq)]
pub struct ProjectionPlan {
    /// Scenes of the call, B.
    pub b: usize,
    /// Particles per scene, N.
    pub n: usize,
    /// Frames per scene of the call, K (a bundle's frames are projected in order, frame
    /// k + 1 first moved by frame k's correction).
    pub k: usize,
    /// Per particle (`[B N]`): the liquid's rest volume in cells (liquid of the pressure
    /// part), else `-(1 + m)` for its material id `m`.
    pub volume: Arc<[f32]>,
    /// The liquid's material id (of the particles with a volume).
    pub liquid: u8,
    /// Particles of each material id in the call (its scenes' frames each count once).
    pub counts: [u64; MATERIALS],
    /// Per scene: [`SCENE_VALUES`] values (the struct's doc), `[B SCENE_VALUES]`.
    pub scenes: Arc<[f32]>,
    /// Nodes held per scene: the largest `side^2` of the call (scene `s`'s nodes start at
    /// `s * nodes`).
    pub nodes: usize,
    /// The pressure part's share of the excess compression removed a frame.
    pub stiffness: f32,
    /// Share of the threshold from which a node is full.
    pub full: f32,
    /// Over-relaxation of the sweeps.
    pub omega: f32,
    /// Red-black sweeps a frame (0: no pressure part).
    pub iterations: usize,
    /// Whether the compressing divergence of the velocity is removed too.
    pub velocity: bool,
    /// Share of the kinetic energy the projection took that is given back.
    pub restore: f32,
    /// Whether positions are clamped into the walls.
    pub walls: bool,
    /// The ropes, the shape-matched bodies and their contact, as f32 (indices exact below
    /// 2^24):
    /// - head, [`SOLIDS_HEAD`] values: where the chain table starts, where the body table
    ///   starts, the ropes' stretch limit, their sweeps a frame, 1 where the long-range
    ///   pairs are on, the contact part's iterations, its restitution, its resting speed;
    ///   from [`MOMENTUM_AT`] the momentum part's reach (0: off), clearance, the position
    ///   lag `(1 + 1/S) / 2` and gravity x, y; from [`REBOUND_AT`] the rebound part's
    ///   restitution, reach, clearance, release, resting speed and gravity x, y;
    /// - per scene, [`SCENE_SOLIDS`] values: its first chain and the chain after its last,
    ///   its first body and the body after its last, the contact distance (domain units; 0:
    ///   no contact), its rebound bodies (its first bodies, jelly; 0: no rebound);
    /// - the chain table, two values a chain: where its elements start, their count; a
    ///   chain's elements two values each, its particle (index in the scene) and its rest
    ///   distance along the chain from its first particle (domain units);
    /// - the body table, [`BODY_VALUES`] a body: where its elements start, their count, the
    ///   shape matching's stiffness and linear share, `A_qq^-1` (row-major); a body's
    ///   elements three values each, its particle and its rest offset from the rest centre.
    pub solids: Arc<[f32]>,
    /// The rebound part's contacts in progress, per scene a table of `rebound^2 + 4 rebound`
    /// contacts ([`EVENT_VALUES`] each): body `a`'s row of `rebound + 4`, the pair with body
    /// `b > a` at column `b`, the walls x = 0, x = 1, y = 0, y = 1 at `rebound + side`;
    /// taken before each call and given back after it (the contacts live with the scenes).
    pub events: Events,
    /// The most rebound bodies of a scene of the call (0: no rebound part).
    pub rebound: usize,
    /// The backend's copy of the arrays on its device, made by the plan's first projection
    /// and shared by its clones: a node's calls of the same scenes reuse one plan
    /// (`model::store`), so its arrays cross to the device once.
    pub device: DeviceCopy,
}

/// A backend's copy of a [`ProjectionPlan`]'s arrays on its device (whatever type the backend
/// keeps), made once and shared by the plan's clones. Plans compare by their arrays: two
/// copies are always equal.
#[derive(Clone, Default)]
pub struct DeviceCopy(Arc<OnceLock<Box<dyn Any + Send + Sync>>>);

impl DeviceCopy {
    /// The copy, made by `make` on the first call; None when an earlier call kept another
    /// type.
    pub fn get_or_init<T: Any + Send + Sync + Clone>(&self, make: impl FnOnce() -> T) -> Option<T> {
        self.0
            .get_or_init(|| Box::new(make()))
            .downcast_ref::<T>()
            .cloned()
    }
}

/// Values of one scene's table of [`ProjectionPlan::events`] in a call of at most `r` rebound
/// bodies a scene.
pub fn event_table_len(r: usize) -> usize {
    r * (r + 4) * EVENT_VALUES
}

/// A call's rebound tables on their way back from the device: the first call of it waits for
/// them and returns them, later calls the same values (empty where the read failed).
pub type TablesLater = Arc<dyn Fn() -> Arc<[f32]> + Send + Sync>;

/// Where a plan's rebound contacts come from and go back to (the scenes' constraint data, on
/// the host): [`EventStore::take`] before a call, [`EventStore::give_back`] with the call's
/// tables after it, read when a scene's contacts are next used (so the host waits for a call
/// only when the next one needs what it left).
pub trait EventStore: Send + Sync {
    /// The tables of the call's scenes (`[B rebound (rebound + 4) EVENT_VALUES]`).
    fn take(&self) -> Vec<f32>;
    /// Hands the scenes the tables a call left (same layout as [`EventStore::take`]'s).
    fn give_back(&self, tables: TablesLater);
}

/// A plan's [`EventStore`], None without the rebound part. Plans compare equal whatever their
/// stores.
#[derive(Clone, Default)]
pub struct Events(pub Option<Arc<dyn EventStore>>);

impl std::fmt::Debug for Events {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("Events")
            .field("store", &self.0.is_some())
            .finish()
    }
}

impl PartialEq for Events {
    fn eq(&self, _: &Self) -> bool {
        true
    }
}

impl std::fmt::Debug for DeviceCopy {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        let made = self.0.get().is_some();
        f.debug_struct("DeviceCopy").field("made", &made).finish()
    }
}

impl PartialEq for DeviceCopy {
    fn eq(&self, _: &Self) -> bool {
        true
    }
}
