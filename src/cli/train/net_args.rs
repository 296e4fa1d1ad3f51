//! The grid network's sizes and shape flags ([`GridNetArgs`]: `--grid`, `--unet-width`,
//! `--levels`, `--latent`, `--hidden`, `--head-hidden`, `--bundle`, `--substeps`,
//! `--interaction*`, `--box-grid`, `--reference`, `--rest-shape`, `--update`), shared by `train` and
//! `report`; `args.rs` turns them into a [`crate::model::grid::GridConfig`].

use clap::Args;

use crate::model::grid::Update;

/// The grid network's sizes (`train` and `report`).
#[derive(Debug, Clone, Args)]
pub struct GridNetArgs {
    /// Grid size n of P2G / U-Net / G2P (a multiple of 2^(levels - 1)).
    #[arg(long, default_value_t = 64, value_parser = crate::cli::flags::at_least_one)]
    pub grid: usize,
    /// U-Net first-level width (channels).
    #[arg(long, default_value_t = 32, value_parser = crate::cli::flags::at_least_one)]
    pub unet_width: usize,
    /// U-Net resolutions.
    #[arg(long, default_value_t = 4, value_parser = crate::cli::flags::at_least_one)]
    pub levels: usize,
    /// Channels the U-Net hands back to the particles.
    #[arg(long, default_value_t = 32, value_parser = crate::cli::flags::at_least_one)]
    pub latent: usize,
    /// Hidden state values per particle (memory cores).
    #[arg(long, default_value_t = 32, value_parser = crate::cli::flags::at_least_one)]
    pub hidden: usize,
    /// Per-particle head width.
    #[arg(long, default_value_t = 64, value_parser = crate::cli::flags::at_least_one)]
    pub head_hidden: usize,
    /// Frames predicted per network call, K (temporal bundling: the U-Net emits K latent
    /// fields, each particle integrates K frames, a rollout of H frames costs ceil(H / K)
    /// calls). 1: the single-frame model.
    #[arg(long, default_value_t = 1, value_parser = crate::cli::flags::bundle)]
    pub bundle: usize,
    /// Network substeps S per frame (1..=8, single-frame models only): the whole network
    /// runs S times at dt / S, each call reading the grid where the last left the particles
    /// (a fast particle's move split into S). `--init-from` any single-frame model.
    #[arg(long, default_value_t = 1, value_parser = crate::cli::flags::substeps)]
    pub substeps: usize,
    /// Rounds of message passing between each particle and its nearest neighbours after
    /// G2P (GNS's processor; 0: none), added to the particle's input to the memory and the
    /// head. `--init-from` a model without it starts it at zero.
    #[arg(long, default_value_t = 0, value_parser = crate::cli::flags::rounds)]
    pub interaction: usize,
    /// The message passing's connectivity radius (domain units, the box is 1).
    #[arg(long, default_value_t = 0.02, value_parser = crate::cli::flags::radius)]
    pub interaction_radius: f64,
    /// Neighbours per particle in the message passing: the nearest within the radius.
    #[arg(long, default_value_t = 12, value_parser = crate::cli::flags::neighbours)]
    pub interaction_neighbours: usize,
    /// The grid whose MPM box, [0.5 / G, 1 - 1.5 / G], the predicted positions are clamped
    /// into (0: the network's --grid, as models saved before the flag). A 32-cell network's
    /// box stops particles at 0.953 of the box, short of the 64- and 128-cell solvers'
    /// walls; 256 (the finest solver) leaves each scene's walls to the network and to the
    /// projection's walls part. `--init-from` may change it (the same weights).
    #[arg(long, default_value_t = 0, value_parser = crate::cli::flags::box_grid)]
    pub box_grid: usize,
    /// Reference positions: first-frame (each particle remembers where it was in the first
    /// frame of its stream, MPM's reference configuration, and the grid sees its
    /// displacement from there; `--init-from` a model without it grows the two input
    /// channels at zero) | none (as models saved before the flag).
    #[arg(long, value_enum, default_value_t = Reference::FirstFrame)]
    pub reference: Reference,
    /// Rest-shape features of the solids: fit (each jelly, snow and rope particle's
    /// deformation gradient fitted to its 8 nearest neighbours of the same material in the
    /// first frame of its stream; Green strain, J - 1 and shape matching's restoring offset
    /// into P2G and the head; `--init-from` a model without them grows them at zero) |
    /// advect (F carried per particle and advected with the predicted velocities' APIC
    /// gradient, F <- (I + dt C) F, started from the fit; the liquid carries J) | none.
    #[arg(long, value_enum, default_value_t = RestShape::None)]
    pub rest_shape: RestShape,
    /// The particle update: free (a per-particle head predicts each velocity change) | grid
    /// (the G2P of a grid velocity-change field the U-Net predicts: a body moves as a body) |
    /// grid+head (the grid field plus the head's per-particle correction). `--init-from` a
    /// free model grows the field's output channels at zero.
    #[arg(long, default_value = "free", value_parser = parse_update)]
    pub update: Update,
}

/// `--rest-shape`: whether the grid model measures the solids' deformation from their rest
/// neighbours.
#[derive(Debug, Clone, Copy, PartialEq, Eq, clap::ValueEnum)]
pub enum RestShape {
    /// No rest-shape features (models saved before the flag existed).
    None,
    /// The deformation gradient fitted to the rest neighbours (`model::grid::rest`).
    Fit,
    /// The deformation gradient advected with the predicted velocity field
    /// (`model::grid::rest::advect`).
    Advect,
}

/// Parses `--update`.
fn parse_update(s: &str) -> Result<Update, String> {
    Update::parse(s).ok_or_else(|| format!("unknown --update {s:?} (free | grid | grid+head)"))
}

/// `--reference`: what the grid model takes as each particle's reference position.
#[derive(Debug, Clone, Copy, PartialEq, Eq, clap::ValueEnum)]
pub enum Reference {
    /// No reference positions (models saved before the flag existed).
    None,
    /// The particle's position in the first frame of its stream.
    FirstFrame,
}

impl GridNetArgs {
    /// These flags as `train` takes them (what `report` prints to reproduce a run).
    pub fn argv(&self) -> Vec<String> {
        let interaction = (self.interaction > 0).then(|| {
            [
                ("--interaction", self.interaction.to_string()),
                (
                    "--interaction-neighbours",
                    self.interaction_neighbours.to_string(),
                ),
                ("--interaction-radius", self.interaction_radius.to_string()),
            ]
        });
        [
            ("--grid", self.grid),
            ("--unet-width", self.unet_width),
            ("--levels", self.levels),
            ("--latent", self.latent),
            ("--hidden", self.hidden),
            ("--head-hidden", self.head_hidden),
            ("--bundle", self.bundle),
        ]
        .into_iter()
        .chain((self.substeps > 1).then_some(("--substeps", self.substeps)))
        .chain((self.box_grid > 0).then_some(("--box-grid", self.box_grid)))
        .flat_map(|(flag, value)| [flag.to_owned(), value.to_string()])
        .chain(
            interaction
                .into_iter()
                .flatten()
                .flat_map(|(flag, value)| [flag.to_owned(), value]),
        )
        .chain(
            (self.reference == Reference::None)
                .then(|| ["--reference".to_owned(), "none".to_owned()])
                .into_iter()
                .flatten(),
        )
        .chain(
            match self.rest_shape {
                RestShape::None => None,
                RestShape::Fit => Some(["--rest-shape".to_owned(), "fit".to_owned()]),
                RestShape::Advect => Some(["--rest-shape".to_owned(), "advect".to_owned()]),
            }
            .into_iter()
            .flatten(),
        )
        .chain(
            (self.update != Update::Free)
                .then(|| ["--update".to_owned(), self.update.name().to_owned()])
                .into_iter()
                .flatten(),
        )
        .collect()
    }
}
