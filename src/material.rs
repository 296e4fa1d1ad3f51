//! The materials a particle can be: one table ([`TABLE`]) of id, name and display colour that
//! every other module reads. The id is what `ParticleFrame.material` carries (`u8`, 0..
//! [`COUNT`]); the name is what scene ids, scene files, `--material-map`, `bag info` and
//! `eval`'s tables print; the colour (RGB) is the one palette of the Foxglove view, the
//! RViz `PointCloud2`, `record --points` and `eval`'s renders (liquid blue, jelly red, snow
//! white, rope orange). The constitutive update of each material lives in
//! [`crate::sim::material`], a grid model's one-hot width in its `model.json`
//! (`GridConfig::materials`). Adding a material: `docs/mpm.md`, "Adding a material".
//!
//! The lowest module of the crate (it uses nothing of it), so `msgs`, `sim`, `eval` and `viz`
//! all depend on it instead of on each other.

use serde::{Deserialize, Serialize};

/// Material id as carried in `ParticleFrame.material`.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Hash, Serialize, Deserialize)]
#[serde(rename_all = "lowercase")]
#[repr(u8)]
pub enum Material {
    /// 0: weakly compressible liquid (mu = 0).
    Liquid = 0,
    /// 1: elastic jelly, fixed-corotated, hardening 0.3.
    Jelly = 1,
    /// 2: snow, fixed-corotated with plasticity and hardening.
    Snow = 2,
    /// 3: rope, a thin line of the elastic model, hardening 0.5.
    Rope = 3,
}

/// One row of [`TABLE`].
#[derive(Clone, Copy, Debug)]
pub struct Row {
    /// The material; its id is the row's index.
    pub material: Material,
    /// Lower-case name, as used in scene ids, scene files and tables.
    pub name: &'static str,
    /// Display colour (RGB).
    pub colour: [u8; 3],
}

impl Row {
    /// A row of [`TABLE`].
    const fn new(material: Material, name: &'static str, colour: [u8; 3]) -> Self {
        Row {
            material,
            name,
            colour,
        }
    }
}

/// Materials there are (the length of [`TABLE`]).
pub const COUNT: usize = 4;

/// Every material, in id order: the one place its name and colour are written.
pub const TABLE: [Row; COUNT] = [
    Row::new(Material::Liquid, "liquid", [40, 120, 255]),
    Row::new(Material::Jelly, "jelly", [230, 60, 90]),
    Row::new(Material::Snow, "snow", [235, 235, 245]),
    Row::new(Material::Rope, "rope", [240, 160, 40]),
];

/// The colour of ids outside [`TABLE`] (grey).
pub const UNKNOWN_COLOUR: [u8; 3] = [128, 128, 128];

// Row k holds the material of id k.
const _: () = {
    let mut k = 0;
    while k < COUNT {
        assert!(
            TABLE[k].material as usize == k,
            "TABLE rows must be in id order"
        );
        k += 1;
    }
};

impl Material {
    /// All materials in id order.
    pub const ALL: [Material; COUNT] = {
        let mut all = [Material::Liquid; COUNT];
        let mut k = 0;
        while k < COUNT {
            all[k] = TABLE[k].material;
            k += 1;
        }
        all
    };

    /// The id stored in frames (0..[`COUNT`]).
    pub fn id(self) -> u8 {
        self as u8
    }

    /// Parses an id; `None` for unknown ids.
    pub fn from_id(id: u8) -> Option<Self> {
        Self::ALL.get(usize::from(id)).copied()
    }

    /// The first id of `ids` that is not a known one ([`Material::from_id`] is `None`), with
    /// its index; None when all are known. A branch-free pass the compiler vectorises comes
    /// first (a frame's 2,500 ids in well under a microsecond, where a search that stops at
    /// the first unknown id took 4), the search only when it finds one.
    pub fn first_unknown(ids: &[u8]) -> Option<(usize, u8)> {
        let known = |id: u8| usize::from(id) < Self::ALL.len();
        if ids.iter().fold(true, |ok, &id| ok & known(id)) {
            return None;
        }
        ids.iter().copied().enumerate().find(|&(_, id)| !known(id))
    }

    /// The material called `name` ([`Material::name`]); `None` for unknown names.
    pub fn from_name(name: &str) -> Option<Self> {
        TABLE
            .iter()
            .find(|row| row.name == name)
            .map(|row| row.material)
    }

    /// Lower-case name, as used in scene ids, scene files and tables.
    pub fn name(self) -> &'static str {
        TABLE[self as usize].name
    }

    /// Display colour (RGB).
    pub fn colour(self) -> [u8; 3] {
        TABLE[self as usize].colour
    }
}

/// The display colour of a material id; [`UNKNOWN_COLOUR`] for ids outside [`TABLE`].
pub fn colour_of(id: u8) -> [u8; 3] {
    Material::from_id(id).map_or(UNKNOWN_COLOUR, Material::colour)
}

/// The names of all materials in id order, e.g. for a message listing them.
pub fn names() -> impl Iterator<Item = &'static str> {
    TABLE.iter().map(|row| row.name)
}

/// Every id with its name, for error messages: `0 liquid, 1 jelly, 2 snow, 3 rope`.
pub fn id_list() -> String {
    let pairs: Vec<String> = Material::ALL
        .iter()
        .map(|m| format!("{} {}", m.id(), m.name()))
        .collect();
    pairs.join(", ")
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn first_unknown_agrees_with_from_id_on_every_id() {
        for id in 0..=u8::MAX {
            let ids = [0, id, 0, id];
            let want = Material::from_id(id).is_none().then_some((1, id));
            assert_eq!(Material::first_unknown(&ids), want, "{id}");
        }
        assert_eq!(Material::first_unknown(&[]), None);
    }

    #[test]
    fn ids_names_and_colours_round_trip() {
        for (k, m) in Material::ALL.into_iter().enumerate() {
            assert_eq!(usize::from(m.id()), k);
            assert_eq!(Material::from_id(m.id()), Some(m));
            assert_eq!(Material::from_name(m.name()), Some(m));
            assert_eq!(colour_of(m.id()), m.colour());
        }
        assert_eq!(Material::from_id(COUNT as u8), None);
        assert_eq!(Material::from_name("lava"), None);
        assert_eq!(colour_of(200), UNKNOWN_COLOUR);
        assert_eq!(
            names().collect::<Vec<_>>().join(","),
            "liquid,jelly,snow,rope"
        );
        assert_eq!(id_list(), "0 liquid, 1 jelly, 2 snow, 3 rope");
    }
}
