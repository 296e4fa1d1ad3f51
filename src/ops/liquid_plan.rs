//! [`LiquidPlan`]: the liquid's projection of one call laid out for a device (plain data;
//! built by `model::constraints::liquid_plan`, run by the CUDA backend's
//! [`NetOps::project_liquid`](super::NetOps::project_liquid), `cuda_liquid*.rs`).

/// Materials a plan keeps apart in its moves (`crate::material::COUNT`).
pub const MATERIALS: usize = 4;

/// Values per scene in [`LiquidPlan::scenes`].
pub const SCENE_VALUES: usize = 10 + MATERIALS;

/// The liquid's projection of one call's K predicted frames (`[K B, N, 4]`) on a device.
///
/// Per scene `s` (row `s` of [`LiquidPlan::scenes`], [`SCENE_VALUES`] each): node spacing
/// `h` (domain units), nodes per side (0: no liquid, the pressure part skipped), the
/// compressed threshold, the band along the walls (width, domain units) and its threshold,
/// the walls `lo` and `hi` (domain units), the time step `dt`, the solids' volume per
/// particle (the liquid's median rest volume, cells), 0 (spare), then the particle spacing of
/// each of the [`MATERIALS`] in the rest frame (domain units; 0 where the scene has none), by
/// which the moves are counted.
#[derive(Clone, Debug, PartialEq)]
pub struct LiquidPlan {
    /// Scenes of the call, B.
    pub b: usize,
    /// Particles per scene, N.
    pub n: usize,
    /// Frames per scene of the call, K (a bundle's frames are projected in order, frame
    /// k + 1 first moved by frame k's correction).
    pub k: usize,
    /// Per particle (`[B N]`): the liquid's rest volume in cells (liquid of the pressure
    /// part), else `-(1 + m)` for its material id `m`.
    pub volume: Vec<f32>,
    /// The liquid's material id (of the particles with a volume).
    pub liquid: u8,
    /// Particles of each material id in the call (its scenes' frames each count once).
    pub counts: [u64; MATERIALS],
    /// Per scene: [`SCENE_VALUES`] values (the struct's doc), `[B SCENE_VALUES]`.
    pub scenes: Vec<f32>,
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
}
