//! The constraint projection on the device (feature `cuda`), one file per part of
//! `model/constraints/` under the same name where there is one: `op.rs` the projection of a
//! call recorded as one custom operation, `call.rs` its kernel (a cube a scene) and
//! `buffers.rs` the arrays its steps share; the parts `solids.rs` (ropes and shape
//! matching), `contact.rs`, `liquid.rs` and `liquid_solve.rs` (the pressure part, walls,
//! velocity update, energy), `momentum.rs` and `momentum_sums.rs`, `rebound.rs`.

pub(in crate::ops) mod buffers;
pub(in crate::ops) mod call;
pub(in crate::ops) mod contact;
pub(in crate::ops) mod liquid;
pub(in crate::ops) mod liquid_solve;
pub(in crate::ops) mod momentum;
pub(in crate::ops) mod momentum_sums;
pub(in crate::ops) mod op;
pub(in crate::ops) mod rebound;
pub(in crate::ops) mod solids;
