//! The liquid's projection on the GPU (`NetOps::project_liquid`, `ops::cuda_liquid*`)
//! against the host's (`SceneShape::project`), on the same predicted frames: three scenes of
//! a liquid column squeezed into the floor and partly pushed through the walls, a bundle of
//! two frames (the second moved by the first's correction), with a shipped model's pressure
//! part and walls (its `restore` on). Feature `cuda`: run on a GPU machine
//! (`tests/gpu/run.sh projection`); CI has no GPU.

#![cfg(feature = "cuda")]

use burn::backend::Cuda;
use burn::tensor::{Tensor, TensorData, TensorPrimitive};
use minflow::material::Material;
use minflow::model::constraints::{liquid_plan, Constraints, SceneShape};
use minflow::ops::NetOps;

type Gpu = Cuda<f32, i32>;

/// The demo's default model's constraint parameters.
fn constraints() -> Constraints {
    let path = concat!(
        env!("CARGO_MANIFEST_DIR"),
        "/models/all-grid-mingru-small-k4/model.json"
    );
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

#[test]
fn the_device_projects_the_liquid_as_the_host_does() {
    let c = constraints();
    assert!(c.pressure.as_ref().is_some_and(|p| p.restore > 0.0));
    let (b, k) = (3usize, 2usize);
    let rests: Vec<Vec<f32>> = (0..b).map(|s| column(0.2 + 0.15 * s as f32)).collect();
    let n = rests[0].len() / 4;
    let ids = vec![Material::Liquid.id(); n];
    let dt = vec![0.004f32; b];
    let nets: Vec<Vec<Vec<f32>>> = (0..k)
        .map(|f| (0..b).map(|s| predicted(&rests[s], s, f)).collect())
        .collect();
    // The host: each scene's frames in order, frame 1 first moved by frame 0's correction.
    let mut host = nets.clone();
    let mut host_moves = 0.0f64;
    for s in 0..b {
        let mut shape = SceneShape::on_grid(&rests[s], 4, &ids, &c, Some(64));
        let mut carried: Option<Vec<f32>> = None;
        for f in 0..k {
            let frame = &mut host[f][s];
            if let Some(offset) = &carried {
                for (row, o) in frame.chunks_exact_mut(4).zip(offset.chunks_exact(2)) {
                    row[0] += o[0];
                    row[1] += o[1];
                }
            }
            let prev = if f == 0 {
                rests[s].clone()
            } else {
                host[f - 1][s].clone()
            };
            let frame = &mut host[f][s];
            let moved = shape.project(&c, (Some(&prev), frame), &ids, dt[s]);
            host_moves += moved.sum[usize::from(Material::Liquid.id())];
            let own = &nets[f][s];
            carried = Some(
                (frame.chunks_exact(4).zip(own.chunks_exact(4)))
                    .flat_map(|(a, o)| [a[0] - o[0], a[1] - o[1]])
                    .collect(),
            );
        }
    }
    // The device: one call of the three scenes.
    let shapes: Vec<SceneShape> = (0..b)
        .map(|s| SceneShape::on_grid(&rests[s], 4, &ids, &c, Some(64)))
        .collect();
    let refs: Vec<&SceneShape> = shapes.iter().collect();
    let material: Vec<u8> = (0..b).flat_map(|_| ids.clone()).collect();
    let plan = liquid_plan(&c, &refs, &material, &dt, k).expect("liquid scenes have a plan");
    let flat: Vec<f32> = nets.iter().flatten().flatten().copied().collect();
    let device = Default::default();
    let out = Tensor::<Gpu, 3>::from_data(TensorData::new(flat, [k * b, n, 4]), &device);
    let (projected, moves) = <Gpu as NetOps>::project_liquid(out.into_primitive().tensor(), &plan)
        .expect("CUDA projects on the device");
    let moves: Vec<f32> = Tensor::<Gpu, 2>::from_primitive(TensorPrimitive::Float(moves))
        .into_data()
        .to_vec()
        .unwrap();
    let liquid = usize::from(Material::Liquid.id());
    let device_moves: f64 = moves.chunks(4).map(|m| f64::from(m[liquid])).sum();
    let got: Vec<f32> = Tensor::<Gpu, 3>::from_primitive(TensorPrimitive::Float(projected))
        .into_data()
        .to_vec()
        .unwrap();
    let want: Vec<f32> = host.iter().flatten().flatten().copied().collect();
    let net: Vec<f32> = nets.iter().flatten().flatten().copied().collect();
    let (mut pos, mut vel, mut moved) = (0.0f32, 0.0f32, 0.0f32);
    for ((g, w), o) in got
        .chunks_exact(4)
        .zip(want.chunks_exact(4))
        .zip(net.chunks_exact(4))
    {
        pos = pos.max((g[0] - w[0]).abs()).max((g[1] - w[1]).abs());
        vel = vel.max((g[2] - w[2]).abs()).max((g[3] - w[3]).abs());
        moved = moved.max((w[1] - o[1]).abs());
    }
    eprintln!("device against host: positions {pos:.2e}, velocities {vel:.2e}; moved {moved:.3}");
    eprintln!("moves (spacings, summed): device {device_moves:.4}, host {host_moves:.4}");
    assert!(
        moved > 1e-3,
        "the host's projection moved nothing ({moved})"
    );
    let apart = (device_moves - host_moves).abs();
    assert!(apart <= 1e-4 * host_moves, "moves differ by {apart}");
    assert!(pos <= 1e-5, "positions differ by {pos}");
    assert!(vel <= 1e-5 / dt[0], "velocities differ by {vel}");
}
