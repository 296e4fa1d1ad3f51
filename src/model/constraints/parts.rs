//! [`Parts`]: which parts of a model's constraints to apply (`--constraints on|off|LIST`),
//! parsed and printed.

#[cfg(doc)]
use super::Constraints;

/// Which parts of a model's [`Constraints`] to apply (`--constraints`): `on` (every part the
/// model has), `off`, or a comma-separated list of `rope`, `jelly`, `snow`, `liquid`,
/// `walls`, `contact`, `momentum`, `rebound`, `pressure`.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub struct Parts {
    /// Rope chain and long-range pairs.
    pub rope: bool,
    /// Jelly shape matching.
    pub jelly: bool,
    /// Snow shape matching.
    pub snow: bool,
    /// Liquid density.
    pub liquid: bool,
    /// Box walls.
    pub walls: bool,
    /// Contact between shape-matched bodies.
    pub contact: bool,
    /// Momentum of free clusters.
    pub momentum: bool,
    /// Rebound of jelly bodies.
    pub rebound: bool,
    /// Liquid pressure projection.
    pub pressure: bool,
}

impl Parts {
    /// Every part.
    pub const ALL: Parts = Parts {
        rope: true,
        jelly: true,
        snow: true,
        liquid: true,
        walls: true,
        contact: true,
        momentum: true,
        rebound: true,
        pressure: true,
    };
    /// No part.
    pub const NONE: Parts = Parts {
        rope: false,
        jelly: false,
        snow: false,
        liquid: false,
        walls: false,
        contact: false,
        momentum: false,
        rebound: false,
        pressure: false,
    };
}

impl Default for Parts {
    fn default() -> Self {
        Parts::ALL
    }
}

impl std::str::FromStr for Parts {
    type Err = String;

    fn from_str(s: &str) -> Result<Self, String> {
        match s.trim() {
            "on" | "all" => return Ok(Parts::ALL),
            "off" | "none" => return Ok(Parts::NONE),
            _ => {}
        }
        let mut parts = Parts::NONE;
        for name in s.split(',').map(str::trim) {
            let flag = match name {
                "rope" => &mut parts.rope,
                "jelly" => &mut parts.jelly,
                "snow" => &mut parts.snow,
                "liquid" => &mut parts.liquid,
                "walls" => &mut parts.walls,
                "contact" => &mut parts.contact,
                "momentum" => &mut parts.momentum,
                "rebound" => &mut parts.rebound,
                "pressure" => &mut parts.pressure,
                other => {
                    return Err(format!(
                        "unknown constraint part {other:?}: expected on, off or a list of \
                         rope, jelly, snow, liquid, walls, contact, momentum, rebound, pressure"
                    ))
                }
            };
            *flag = true;
        }
        Ok(parts)
    }
}

impl std::fmt::Display for Parts {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        if *self == Parts::ALL {
            return f.write_str("on");
        }
        if *self == Parts::NONE {
            return f.write_str("off");
        }
        let names = [
            (self.rope, "rope"),
            (self.jelly, "jelly"),
            (self.snow, "snow"),
            (self.liquid, "liquid"),
            (self.walls, "walls"),
            (self.contact, "contact"),
            (self.momentum, "momentum"),
            (self.rebound, "rebound"),
            (self.pressure, "pressure"),
        ];
        let on: Vec<&str> = names.iter().filter(|(b, _)| *b).map(|(_, n)| *n).collect();
        f.write_str(&on.join(","))
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::model::constraints::Constraints;

    #[test]
    fn parts_parse_and_print() {
        assert_eq!("on".parse::<Parts>().unwrap(), Parts::ALL);
        assert_eq!("off".parse::<Parts>().unwrap(), Parts::NONE);
        let p: Parts = "rope,liquid".parse().unwrap();
        assert!(p.rope && p.liquid && !p.jelly && !p.snow && !p.walls);
        assert_eq!(p.to_string(), "rope,liquid");
        assert!("ropes".parse::<Parts>().is_err());
    }

    #[test]
    fn selecting_no_part_leaves_nothing() {
        let c = Constraints::defaults();
        assert!(c.select(Parts::NONE).is_empty());
        assert!(!c.select("jelly".parse().unwrap()).is_empty());
        assert!(c.select("snow".parse().unwrap()).is_empty()); // the defaults have no snow
    }
}
