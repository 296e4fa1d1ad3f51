//! The projection on the GPU (`NetOps::project_constraints`, `ops::cuda::projection`:
//! `op`, `call`, `liquid*`, `solids`, `contact`, `rebound`, `momentum`) against the
//! host's (`SceneShape::project`), on the same predicted frames, a bundle of two frames (the
//! second moved by the first's correction), with `-small-k4`'s parts (its `restore` on):
//! three scenes of a liquid column squeezed into the floor and partly pushed through the
//! walls; three of every material, a rope stretched, two jelly disks driven into each other
//! and a snow block beside the liquid; then with `-small-k4-mixed`'s (momentum and rebound
//! on) the same scenes coming from frames in which the disks were apart and closing, the
//! pieces flying free. Feature `cuda`: run on a GPU machine (`tests/gpu/run.sh projection`);
//! CI has no GPU.

#![cfg(feature = "cuda")]

use burn::backend::Cuda;
use burn::tensor::{Tensor, TensorData, TensorPrimitive};
use minflow::material::Material;
use minflow::model::constraints::{projection_plan, Constraints, SceneShape};
use minflow::ops::NetOps;

type Gpu = Cuda<f32, i32>;

/// `models/all-grid-mingru-small-k4`'s constraint parameters.
fn constraints() -> Constraints {
    constraints_of("all-grid-mingru-small-k4")
}

/// The constraint parameters of shipped model `name`.
fn constraints_of(name: &str) -> Constraints {
    let path = format!("{}/models/{name}/model.json", env!("CARGO_MANIFEST_DIR"));
    let meta: serde_json::Value = serde_json::from_slice(&std::fs::read(path).unwrap()).unwrap();
    serde_json::from_value(meta["constraints"].clone()).unwrap()
}

/// A 30 x 40 column of liquid at spacing 1/128 from `(x0, 0.05)`, at rest (`[N, 4]`).
fn column(x0: f32) -> Vec<f32> {
    let mut f = Vec::new();
    for i in 0..30 {
        for j in 0..40 {
            f.extend([x0 + i as f32 / 128.0, 0.05 + j as f32 / 128.0, 0.0, 0.0]);
        }
    }
    f
}

/// The network's frame `k` of scene `s`: the column fallen and squeezed towards the floor
/// (by more each frame and scene), its lowest rows through it, with a swirl in the velocity.
fn predicted(rest: &[f32], s: usize, k: usize) -> Vec<f32> {
    let squeeze = 0.75 - 0.05 * (s + k) as f32;
    let mut f = rest.to_vec();
    for (p, row) in f.chunks_exact_mut(4).enumerate() {
        row[1] = 0.04 + (row[1] - 0.05) * squeeze - 0.002 * k as f32;
        row[2] = 0.3 * ((p % 7) as f32 - 3.0);
        row[3] = -1.5 + 0.1 * ((p % 5) as f32);
    }
    f
}

/// The host's projection of `nets` (`[K][B][N 4]`: frame k of scene s), each scene's frames
/// in order, frame k + 1 first moved by frame k's correction; the projected frames and the
/// summed moves per material (spacings).
fn on_host(
    c: &Constraints,
    (rests, inputs): (&[Vec<f32>], &[Vec<f32>]),
    ids: &[u8],
    nets: &[Vec<Vec<f32>>],
    dt: &[f32],
) -> (Vec<f32>, [f64; 4]) {
    let mut host = nets.to_vec();
    let mut moves = [0.0f64; 4];
    for (s, rest) in rests.iter().enumerate() {
        let mut shape = SceneShape::on_grid(rest, 4, ids, c, Some(64));
        let mut carried: Option<Vec<f32>> = None;
        for f in 0..nets.len() {
            let frame = &mut host[f][s];
            if let Some(offset) = &carried {
                for (row, o) in frame.chunks_exact_mut(4).zip(offset.chunks_exact(2)) {
                    row[0] += o[0];
                    row[1] += o[1];
                }
            }
            let prev = if f == 0 {
                inputs[s].clone()
            } else {
                host[f - 1][s].clone()
            };
            let frame = &mut host[f][s];
            let moved = shape.project(c, (Some(&prev), frame), ids, dt[s]);
            for (m, v) in moves.iter_mut().enumerate() {
                *v += moved.sum[m];
            }
            let own = &nets[f][s];
            carried = Some(
                (frame.chunks_exact(4).zip(own.chunks_exact(4)))
                    .flat_map(|(a, o)| [a[0] - o[0], a[1] - o[1]])
                    .collect(),
            );
        }
    }
    (host.into_iter().flatten().flatten().collect(), moves)
}

/// The device's projection of the same frames, one call of every scene.
fn on_device(
    c: &Constraints,
    (rests, inputs): (&[Vec<f32>], &[Vec<f32>]),
    ids: &[u8],
    nets: &[Vec<Vec<f32>>],
    dt: &[f32],
) -> (Vec<f32>, [f64; 4]) {
    let (b, k, n) = (rests.len(), nets.len(), ids.len());
    let shapes: Vec<SceneShape> = (rests.iter())
        .map(|rest| SceneShape::on_grid(rest, 4, ids, c, Some(64)))
        .collect();
    let refs: Vec<&SceneShape> = shapes.iter().collect();
    let material: Vec<u8> = (0..b).flat_map(|_| ids.to_vec()).collect();
    let plan = projection_plan(c, &refs, &material, dt, k).expect("the scenes have a plan");
    let flat: Vec<f32> = nets.iter().flatten().flatten().copied().collect();
    let device = Default::default();
    let out = Tensor::<Gpu, 3>::from_data(TensorData::new(flat, [k * b, n, 4]), &device);
    let input: Vec<f32> = inputs.iter().flatten().copied().collect();
    let input = Tensor::<Gpu, 3>::from_data(TensorData::new(input, [b, n, 4]), &device);
    let input = Some(input.into_primitive().tensor());
    let (projected, moves) =
        <Gpu as NetOps>::project_constraints(out.into_primitive().tensor(), input, &plan)
            .expect("CUDA projects on the device");
    let moves: Vec<f32> = Tensor::<Gpu, 2>::from_primitive(TensorPrimitive::Float(moves))
        .into_data()
        .to_vec()
        .unwrap();
    let mut sums = [0.0f64; 4];
    for row in moves.chunks(4) {
        for (m, v) in sums.iter_mut().enumerate() {
            *v += f64::from(row[m]);
        }
    }
    let got = Tensor::<Gpu, 3>::from_primitive(TensorPrimitive::Float(projected))
        .into_data()
        .to_vec()
        .unwrap();
    (got, sums)
}

/// Checks the device's projection against the host's: positions to 1e-5, velocities to
/// 1e-5 over `dt`, each material's summed moves to 1e-4 of the host's; and that the host
/// moved each material of `moved_ids` by more than 1e-3 somewhere. Returns the host's frames.
fn agree(
    c: &Constraints,
    (rests, inputs, ids): (&[Vec<f32>], &[Vec<f32>], &[u8]),
    nets: &[Vec<Vec<f32>>],
    dt: f32,
    moved_ids: &[Material],
) -> Vec<f32> {
    let dts = vec![dt; rests.len()];
    let (want, host_moves) = on_host(c, (rests, inputs), ids, nets, &dts);
    let (got, device_moves) = on_device(c, (rests, inputs), ids, nets, &dts);
    let net: Vec<f32> = nets.iter().flatten().flatten().copied().collect();
    let (mut pos, mut vel) = (0.0f32, 0.0f32);
    let mut moved = [0.0f32; 4];
    for (i, ((g, w), o)) in (got.chunks_exact(4))
        .zip(want.chunks_exact(4))
        .zip(net.chunks_exact(4))
        .enumerate()
    {
        pos = pos.max((g[0] - w[0]).abs()).max((g[1] - w[1]).abs());
        vel = vel.max((g[2] - w[2]).abs()).max((g[3] - w[3]).abs());
        let m = usize::from(ids[i % ids.len()]);
        moved[m] = moved[m].max((w[0] - o[0]).abs()).max((w[1] - o[1]).abs());
    }
    eprintln!("device against host: positions {pos:.2e}, velocities {vel:.2e}; moved {moved:?}");
    eprintln!("moves (spacings, summed): device {device_moves:?}, host {host_moves:?}");
    for m in moved_ids {
        let m = usize::from(m.id());
        assert!(moved[m] > 1e-3, "the host moved nothing of material {m}");
    }
    for m in 0..4 {
        let apart = (device_moves[m] - host_moves[m]).abs();
        assert!(
            apart <= 1e-4 * host_moves[m].max(1.0),
            "moves of {m} differ by {apart}"
        );
    }
    assert!(pos <= 1e-5, "positions differ by {pos}");
    assert!(vel <= 1e-5 / dt, "velocities differ by {vel}");
    want
}

#[test]
fn the_device_projects_the_liquid_as_the_host_does() {
    let c = constraints();
    assert!(c.pressure.as_ref().is_some_and(|p| p.restore > 0.0));
    let (b, k) = (3usize, 2usize);
    let rests: Vec<Vec<f32>> = (0..b).map(|s| column(0.2 + 0.15 * s as f32)).collect();
    let n = rests[0].len() / 4;
    let ids = vec![Material::Liquid.id(); n];
    let nets: Vec<Vec<Vec<f32>>> = (0..k)
        .map(|f| (0..b).map(|s| predicted(&rests[s], s, f)).collect())
        .collect();
    agree(
        &c,
        (&rests, &rests, &ids),
        &nets,
        0.004,
        &[Material::Liquid],
    );
}

/// A scene of every material at rest, spacing 1/128: a 20 x 20 liquid column from `(0.1 +
/// shift, 0.05)`, a rope of 60 particles along `y = 0.7`, two jelly disks of radius 0.05 with
/// 0.14 between their centres, and an 8 x 8 snow block (`[N, 4]` rows, material ids).
fn mixed(shift: f32) -> (Vec<f32>, Vec<u8>) {
    let h = 1.0 / 128.0;
    let (mut f, mut ids) = (Vec::new(), Vec::new());
    let mut put = |x: f32, y: f32, m: Material| {
        f.extend([x, y, 0.0, 0.0]);
        ids.push(m.id());
    };
    for i in 0..20 {
        for j in 0..20 {
            put(
                0.1 + shift + i as f32 * h,
                0.05 + j as f32 * h,
                Material::Liquid,
            );
        }
    }
    for i in 0..60 {
        put(0.1 + i as f32 * h, 0.7, Material::Rope);
    }
    for cx in [0.5 + shift, 0.64 + shift] {
        for i in -7i32..=7 {
            for j in -7i32..=7 {
                let (x, y) = (i as f32 * h, j as f32 * h);
                if x * x + y * y <= 0.05 * 0.05 {
                    put(cx + x, 0.4 + y, Material::Jelly);
                }
            }
        }
    }
    for i in 0..8 {
        for j in 0..8 {
            put(0.8 + i as f32 * h, 0.1 + j as f32 * h, Material::Snow);
        }
    }
    (f, ids)
}

/// The network's frame `k` of a [`mixed`] scene shifted by `shift`: the liquid squeezed into
/// the floor, the rope stretched 1.35x and bent, the two disks turned, roughened and driven
/// into each other by 0.03 + 0.005 k each (closing at 3 domain units a time unit), the snow
/// dropped.
fn mixed_predicted(rest: &[f32], ids: &[u8], shift: f32, k: usize) -> Vec<f32> {
    let mut f = rest.to_vec();
    let (turn, into) = (0.15f32, 0.03 + 0.005 * k as f32);
    for (p, row) in f.chunks_exact_mut(4).enumerate() {
        let wiggle = (13.0 * p as f32).sin();
        match Material::from_id(ids[p]) {
            Some(Material::Liquid) => {
                row[1] = 0.04 + (row[1] - 0.05) * (0.75 - 0.05 * k as f32);
                row[2] = 0.3 * ((p % 7) as f32 - 3.0);
                row[3] = -1.5 + 0.1 * ((p % 5) as f32);
            }
            Some(Material::Rope) => {
                row[0] = 0.1 + (row[0] - 0.1) * 1.35;
                row[1] += 0.01 * (7.0 * p as f32).sin();
                (row[2], row[3]) = (0.5, -1.0);
            }
            Some(Material::Jelly) => {
                let left = row[0] < 0.57 + shift;
                let cx = if left { 0.5 + shift } else { 0.64 + shift };
                let (x, y) = (row[0] - cx, row[1] - 0.4);
                let (s, c) = turn.sin_cos();
                let side = if left { 1.0 } else { -1.0 };
                row[0] = cx + c * x - s * y + 0.002 * wiggle + side * into;
                row[1] = 0.4 + s * x + c * y - 0.002 * wiggle;
                (row[2], row[3]) = (1.5 * side, 0.2 * wiggle);
            }
            _ => {
                row[1] -= 0.01;
                row[3] = -2.0;
            }
        }
    }
    f
}

#[test]
fn the_device_projects_ropes_bodies_and_their_contact_as_the_host_does() {
    let c = constraints();
    assert!(c.rope.is_some() && c.jelly.is_some() && c.contact.is_some());
    let (b, k) = (3usize, 2usize);
    let shifts: Vec<f32> = (0..b).map(|s| 0.02 * s as f32).collect();
    let scenes: Vec<(Vec<f32>, Vec<u8>)> = shifts.iter().map(|&s| mixed(s)).collect();
    let ids = scenes[0].1.clone();
    assert!(scenes.iter().all(|(_, i)| *i == ids));
    let rests: Vec<Vec<f32>> = scenes.into_iter().map(|(r, _)| r).collect();
    let nets: Vec<Vec<Vec<f32>>> = (0..k)
        .map(|f| {
            (0..b)
                .map(|s| mixed_predicted(&rests[s], &ids, shifts[s], f))
                .collect()
        })
        .collect();
    let moved = [Material::Liquid, Material::Jelly, Material::Rope];
    let host = agree(&c, (&rests, &rests, &ids), &nets, 0.004, &moved);
    // The contact acted: the left disk, driven right at 1.5, leaves to the left.
    let n = ids.len();
    let left: Vec<f32> = (host[..n * 4].chunks_exact(4))
        .zip(rests[0].chunks_exact(4).zip(&ids))
        .filter(|(_, (rest, &m))| m == Material::Jelly.id() && rest[0] < 0.57)
        .map(|(r, _)| r[2])
        .collect();
    let mean = left.iter().sum::<f32>() / left.len() as f32;
    assert!(mean < -0.5, "the left disk's mean velocity {mean}");
}

/// Frame `k` of a [`mixed`] scene shifted by `shift` predicted after two disks hit each
/// other: [`mixed_predicted`]'s, but the disks 0.01 + 0.002 k further apart than at rest (past
/// the rebound's release, within its reach) and parting slowly (0.2 each).
fn bounce_predicted(rest: &[f32], ids: &[u8], shift: f32, k: usize) -> Vec<f32> {
    let mut f = mixed_predicted(rest, ids, shift, k);
    for ((row, r), &m) in f.chunks_exact_mut(4).zip(rest.chunks_exact(4)).zip(ids) {
        if m == Material::Jelly.id() {
            let side = if r[0] < 0.57 + shift { -1.0 } else { 1.0 };
            row[0] = r[0] + side * (0.01 + 0.002 * k as f32);
            row[1] = r[1];
            (row[2], row[3]) = (0.2 * side, 0.0);
        }
    }
    f
}

#[test]
fn the_device_keeps_momentum_and_rebound_as_the_host_does() {
    let c = constraints_of("all-grid-mingru-small-k4-mixed");
    assert!(c.momentum.is_some() && c.rebound.is_some());
    let (b, k) = (3usize, 2usize);
    let shifts: Vec<f32> = (0..b).map(|s| 0.02 * s as f32).collect();
    let scenes: Vec<(Vec<f32>, Vec<u8>)> = shifts.iter().map(|&s| mixed(s)).collect();
    let ids = scenes[0].1.clone();
    let rests: Vec<Vec<f32>> = scenes.into_iter().map(|(r, _)| r).collect();
    // The frame before: the disks 0.04 further apart each (beyond the rebound's reach) and
    // closing at 2 each, the rope and the snow flying up and right.
    let inputs: Vec<Vec<f32>> = (rests.iter().zip(&shifts))
        .map(|(rest, &shift)| {
            let mut f = rest.clone();
            for (row, &m) in f.chunks_exact_mut(4).zip(&ids) {
                if m == Material::Jelly.id() {
                    let side = if row[0] < 0.57 + shift { -1.0 } else { 1.0 };
                    row[0] += 0.04 * side;
                    row[2] = -2.0 * side;
                } else if m != Material::Liquid.id() {
                    (row[2], row[3]) = (0.7, 1.2);
                }
            }
            f
        })
        .collect();
    let nets: Vec<Vec<Vec<f32>>> = (0..k)
        .map(|f| {
            (0..b)
                .map(|s| bounce_predicted(&rests[s], &ids, shifts[s], f))
                .collect()
        })
        .collect();
    let moved = [
        Material::Liquid,
        Material::Jelly,
        Material::Rope,
        Material::Snow,
    ];
    let host = agree(&c, (&rests, &inputs, &ids), &nets, 0.004, &moved);
    // The rebound acted: without it the disks end elsewhere.
    let without = Constraints {
        rebound: None,
        ..c.clone()
    };
    let dts = vec![0.004; b];
    let (other, _) = on_host(&without, (&rests, &inputs), &ids, &nets, &dts);
    let jelly = |f: &[f32]| -> Vec<f32> {
        (f.chunks_exact(4).enumerate())
            .filter(|(i, _)| ids[i % ids.len()] == Material::Jelly.id())
            .map(|(_, r)| r[0])
            .collect()
    };
    let apart = (jelly(&host).iter().zip(jelly(&other)))
        .map(|(a, b)| (a - b).abs())
        .fold(0.0f32, f32::max);
    assert!(apart > 1e-3, "the rebound moved the disks by {apart}");
}
