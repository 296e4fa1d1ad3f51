"""PyTorch timing reference for minflow's grid architecture (`train --arch grid`, docs/grid.md).

The same network and training step as src/model/grid/ and src/train/grid/, on synthetic data
already on the GPU, so that burn's CUDA backend and PyTorch are timed on the same GPU at the
same precision. One optimizer step (`GridTrainer::fit`) is `sequence_loss` (P rollout steps of
`GridModel::step`, the first `teacher` reading the true frame, the rest the model's own
prediction, the memory state carried through all P), backward, per-parameter gradient-norm
clipping and Adam (eps 1e-8). `GridModel::step` is: P2G of [1, velocities, material one-hot]
with MPM's quadratic B-spline weights (transfer.rs) -> grid [m/4, per-mass values, 2 wall
masks] -> U-Net (unet.rs) -> G2P -> per-particle memory (memory.rs: minGRU / minLSTM / GRU /
LSTM / none) -> SiLU head MLP -> trapezoid integration, clamped into the box. Written for this
comparison from the Rust sources; it is not minflow's model and is not used to train.

    python3 tools/torch_grid_reference.py --memory none,mingru,minlstm --precision fp32 --batch 16

prints one line per (memory, precision): samples per second from the median step time (after
`--warmup` steps, which are left out), with the parameter count (to check against minflow's)
and the peak allocated GPU memory, then the caching allocator's peak reserved memory (what
compares with cubecl's pool, `bench train`'s `peak MiB`). Runs on a CPU too (`--device cpu`, small `--steps`), as a
sanity check only.

Not matched (none changes the work per step): the batch is drawn once on the device (minflow
uploads each batch from the host), the learning rate is constant (minflow's decays by cosine),
the initial weights are PyTorch's defaults (minflow draws burn's on the CPU from its seed) and
the normalisation constants are 1 / 0 (minflow fits them on the training split).
"""

import argparse
import math
import time

import torch
import torch.nn as nn
import torch.nn.functional as F

MATERIALS = 4  # src/model/grid/mod.rs MATERIALS


def g(x):  # src/model/minrnn.rs g: x + 0.5 for x >= 0, sigmoid(x) otherwise
    return torch.where(x >= 0, x + 0.5, torch.sigmoid(x))


# --- Memory cells, one step each (memory.rs Memory::step; minrnn.rs / rnn.rs `step`). ---
# Each takes u [B N, d_in] and the state (None = MemoryState::Empty) and returns (out, state).
class MinGru(nn.Module):  # minrnn.rs MinGru::step
    def __init__(self, d_in, h):
        super().__init__()
        self.h = h
        self.to_hidden_and_gate = nn.Linear(d_in, 2 * h)  # [h~ pre, z pre]
        self.to_out = nn.Linear(h, h)

    def forward(self, x, h):
        hg = self.to_hidden_and_gate(x)
        tilde, z = g(hg[:, : self.h]), torch.sigmoid(hg[:, self.h :])
        nxt = z * tilde if h is None else (1 - z) * h + z * tilde
        return self.to_out(nxt), nxt


class MinLstm(nn.Module):  # minrnn.rs MinLstm::step
    def __init__(self, d_in, h):
        super().__init__()
        self.h = h
        self.to_hidden_and_gates = nn.Linear(d_in, 3 * h)  # [h~ pre, f pre, i pre]
        self.to_out = nn.Linear(h, h)

    def forward(self, x, h):
        n = self.h
        hfi = self.to_hidden_and_gates(x)
        tilde = g(hfi[:, :n])
        f, i = torch.sigmoid(hfi[:, n : 2 * n]), torch.sigmoid(hfi[:, 2 * n :])
        norm = f + i
        f, i = f / norm, i / norm
        nxt = i * tilde if h is None else f * h + i * tilde
        return self.to_out(nxt), nxt


class Gru(nn.Module):  # rnn.rs Gru::step / Gru::cell (W with bias, U without; h0 = 0)
    def __init__(self, d_in, h):
        super().__init__()
        self.h = h
        self.input = nn.Linear(d_in, 3 * h)
        self.recurrent_gates = nn.Linear(h, 2 * h, bias=False)
        self.recurrent_candidate = nn.Linear(h, h, bias=False)

    def forward(self, x, h):
        n, xp = self.h, self.input(x)
        h = xp.new_zeros(x.shape[0], n) if h is None else h
        gates = self.recurrent_gates(h)
        z = torch.sigmoid(xp[:, :n] + gates[:, :n])
        r = torch.sigmoid(xp[:, n : 2 * n] + gates[:, n:])
        cand = torch.tanh(xp[:, 2 * n :] + self.recurrent_candidate(r * h))
        h = (1 - z) * h + z * cand
        return h, h


class Lstm(nn.Module):  # rnn.rs Lstm::step / Lstm::cell ([i, f, o, c~]; state (h, c))
    def __init__(self, d_in, h):
        super().__init__()
        self.h = h
        self.input = nn.Linear(d_in, 4 * h)
        self.recurrent = nn.Linear(h, 4 * h, bias=False)

    def forward(self, x, s):
        n, xp = self.h, self.input(x)
        h, c = (xp.new_zeros(x.shape[0], n),) * 2 if s is None else s
        pre = xp + self.recurrent(h)
        i, f, o = (torch.sigmoid(pre[:, k * n : (k + 1) * n]) for k in range(3))
        c = f * c + i * torch.tanh(pre[:, 3 * n :])
        h = o * torch.tanh(c)
        return h, (h, c)


CELLS = {"mingru": MinGru, "minlstm": MinLstm, "gru": Gru, "lstm": Lstm}


# --- U-Net (src/model/grid/unet.rs). ---
class ConvBlock(nn.Module):  # unet.rs ConvBlock: two 3x3 same-padding convs, SiLU after each
    def __init__(self, c_in, c_out):
        super().__init__()
        self.a = nn.Conv2d(c_in, c_out, 3, padding=1)
        self.b = nn.Conv2d(c_out, c_out, 3, padding=1)

    def forward(self, x):
        return F.silu(self.b(F.silu(self.a(x))))


class UNet(nn.Module):  # unet.rs UNetConfig::init / UNet::forward
    def __init__(self, c_in, c_out, width=32, levels=4):
        super().__init__()
        w = [width << min(l, 2) for l in range(levels)]  # UNetConfig::level_width: 32,64,128,128
        self.down = nn.ModuleList(ConvBlock(c_in if l == 0 else w[l - 1], w[l]) for l in range(levels))
        self.up = nn.ModuleList(ConvBlock(w[l + 1] + w[l], w[l]) for l in range(levels - 1))
        self.head = nn.Conv2d(w[0], c_out, 1)

    def forward(self, x):
        skips = []
        for l, block in enumerate(self.down):
            if l > 0:
                x = F.avg_pool2d(x, 2)  # avg_pool2d([2, 2], [2, 2], no padding)
            x = block(x)
            skips.append(x)
        skips.pop()
        for block in reversed(self.up):  # nearest 2x upsample, cat [upsampled, skip], block
            x = block(torch.cat([F.interpolate(x, scale_factor=2, mode="nearest"), skips.pop()], 1))
        return self.head(x)


# --- Particle <-> grid transfers (src/model/grid/transfer.rs). ---
def stencil(pos, n):
    """transfer.rs stencil: flat node indices [B N 9] into a [B n^2, C] grid, weights [B, N, 9]."""
    b, p, _ = pos.shape
    dx = 1.0 / n
    gp = pos.detach().clamp(0.5 * dx, 1.0 - 1.5 * dx - 1e-5) * n  # bounds(n), grid units
    base = torch.floor(gp - 0.5)
    f = gp - base
    w = torch.stack([0.5 * (1.5 - f) ** 2, 0.75 - (f - 1.0) ** 2, 0.5 * (f - 0.5) ** 2], 3)  # [B,N,2,3]
    weight = (w[:, :, 0, :, None] * w[:, :, 1, None, :]).reshape(b, p, 9)  # k = 3 i + j, i on x
    base = base.long()
    k = torch.arange(9, device=pos.device)
    offsets = (k // 3) * n + k % 3
    rows = torch.arange(b, device=pos.device).view(b, 1, 1) * (n * n)
    index = base[..., 0:1] * n + base[..., 1:2] + rows + offsets  # [B, N, 9]
    return index.reshape(-1), weight


def p2g(index, weight, values, n):
    """transfer.rs p2g: sum_p w_ip v_p per node, [B, n^2, C] (select_assign Add = index_add)."""
    b, p, c = values.shape
    spread = (weight.unsqueeze(3) * values.unsqueeze(2)).reshape(b * p * 9, c)
    grid = values.new_zeros(b * n * n, c).index_add(0, index, spread)
    return grid.view(b, n * n, c)


def g2p(index, weight, grid):
    """transfer.rs g2p: sum_i w_ip g_i per particle, [B, N, C] (select = index_select)."""
    b, _, c = grid.shape
    picked = grid.reshape(-1, c).index_select(0, index).view(b, -1, 9, c)
    return (picked * weight.unsqueeze(3)).sum(2)


def walls(n, device):  # mod.rs walls: [1, n^2, 2] masks of nodes with index < 3 or > n - 3
    i = torch.arange(n, device=device)
    wall = ((i < 3) | (i + 3 > n)).float()
    return torch.stack([wall.view(n, 1).expand(n, n), wall.view(1, n).expand(n, n)], 2).reshape(1, n * n, 2)


# --- The model (src/model/grid/mod.rs GridConfig::init / GridModel::step). ---
class GridModel(nn.Module):
    def __init__(self, memory, n=64, window=2, unet_width=32, levels=4, latent=32, hidden=32, head_hidden=64):
        super().__init__()
        self.n, self.t = n, window
        c_grid = 1 + 2 * window + MATERIALS + 2  # grid_channels
        d_u = latent + 2 * window + MATERIALS + 2  # latent + own_features
        self.unet = UNet(c_grid, latent, unet_width, levels)
        self.memory = CELLS[memory](d_u, hidden) if memory != "none" else None
        self.head_a = nn.Linear(d_u + (hidden if self.memory is not None else 0), head_hidden)
        self.head_b = nn.Linear(head_hidden, head_hidden)
        self.head_out = nn.Linear(head_hidden, 2)
        nn.init.zeros_(self.head_out.weight)  # head_zero_init (Initializer::Zeros: weight and bias)
        nn.init.zeros_(self.head_out.bias)
        # Normalisation constants (fit_stats fills them from data; their values cost nothing).
        for name, v in [("vel_scale", 1.0), ("dv_mean", 0.0), ("dv_scale", 1.0)]:
            self.register_buffer(name, torch.full((2,), v))
        self.register_buffer("walls", walls(n, "cpu"))

    def step(self, pos, vel, material, dt, state):
        """pos [B,N,2], vel [B,N,2T] (oldest first), material [B,N,4], dt [B] -> (pos', v', state')."""
        b, p, _ = pos.shape
        n, t = self.n, self.t
        vel = vel / self.vel_scale.repeat(t)
        index, weight = stencil(pos, n)  # P2G
        splat = p2g(index, weight, torch.cat([pos.new_ones(b, p, 1), vel, material], 2), n)
        mass = splat[..., :1]
        per_mass = splat[..., 1:] / mass.clamp_min(1e-6)
        grid = torch.cat([mass * 0.25, per_mass, self.walls.expand(b, -1, -1)], 2)  # [B, n^2, C]
        grid = grid.transpose(1, 2).reshape(b, -1, n, n)
        out = self.unet(grid)  # U-Net, then G2P
        out = out.reshape(b, out.shape[1], n * n).transpose(1, 2)  # [B, n^2, L]
        u = torch.cat([g2p(index, weight, out), vel, material, pos], 2).reshape(b * p, -1)
        features = u
        if self.memory is not None:  # Memory::step
            m, state = self.memory(u, state)
            features = torch.cat([u, m], 1)
        h = F.silu(self.head_b(F.silu(self.head_a(features))))
        dv = self.head_out(h).view(b, p, 2) * self.dv_scale + self.dv_mean
        v = vel[..., 2 * (t - 1) :] * self.vel_scale
        v_next = v + dv
        pos = pos + (v + v_next) * (0.5 * dt.view(b, 1, 1))  # trapezoid
        dx = 1.0 / n
        return pos.clamp(0.5 * dx, 1.0 - 1.5 * dx), v_next, state


def sequence_loss(model, frames, material, dt, steps, teacher, noise):
    """src/train/grid/rollout_loss.rs sequence_loss; frames [B, T + P, N, 4] (x, y, vx, vy)."""
    t = model.t
    b = frames.shape[0]
    dv_scale = model.dv_scale
    noisy = (lambda v: v + torch.randn_like(v) * dv_scale * noise) if noise > 0 else (lambda v: v)
    history = [noisy(frames[:, k, :, 2:4]) for k in range(t)]
    pos = frames[:, t - 1, :, 0:2]
    state = None
    pos_scale = dv_scale * dt.view(b, 1, 1)
    total = 0.0
    for p in range(steps):
        pos_out, vel_out, state = model.step(pos, torch.cat(history[-t:], 2), material, dt, state)
        target = frames[:, t + p]
        lv = (((vel_out - target[..., 2:4]) / dv_scale) ** 2).mean()
        lx = (((pos_out - target[..., 0:2]) / pos_scale) ** 2).mean()
        total = total + lv + lx
        if p + 1 < teacher:  # teacher forcing: the next step reads the true frame
            pos = target[..., 0:2]
            history.append(noisy(target[..., 2:4]))
        else:
            pos = pos_out
            history.append(vel_out)
    return total / max(steps, 1)


@torch.no_grad()
def clip_per_parameter(params, max_norm):
    """burn's GradientClipping::Norm, as Adam's adaptor applies it: each parameter's gradient
    separately (burn-optim grad_clipping/base.rs clip_by_norm), not torch's global norm."""
    grads = [q.grad for q in params if q.grad is not None]
    norms = torch.stack(torch._foreach_norm(grads))
    coefs = (max_norm / (norms + torch.finfo(torch.float32).tiny)).clamp(max=1.0)
    for gr, c in zip(grads, coefs.unbind()):
        gr.mul_(c)


def synthetic(b, frames, particles, device):
    """A batch of random frames [B, T + P, N, 4], one-hot materials [B, N, 4] and dt [B]."""
    pos = torch.rand(b, frames, particles, 2, device=device) * 0.9 + 0.05
    vel = torch.randn(b, frames, particles, 2, device=device) * 0.5
    material = F.one_hot(torch.randint(0, MATERIALS, (b, particles), device=device), MATERIALS)
    return torch.cat([pos, vel], 3), material.float(), torch.full((b,), 0.016, device=device)


def set_tf32(on):
    """fp32: full-FP32 cuBLAS products and cuDNN convolutions; tf32: TF32 tensor cores for both."""
    if hasattr(torch.backends.cuda.matmul, "fp32_precision"):  # torch >= 2.9 (old flags deprecated)
        torch.backends.cuda.matmul.fp32_precision = "tf32" if on else "ieee"
        torch.backends.cudnn.conv.fp32_precision = "tf32" if on else "ieee"
    else:
        torch.backends.cuda.matmul.allow_tf32 = on
        torch.backends.cudnn.allow_tf32 = on


def bench(memory, a, tf32, device):
    set_tf32(tf32)
    torch.manual_seed(0)
    cuda = device.type == "cuda"
    sync = torch.cuda.synchronize if cuda else (lambda: None)
    model = GridModel(memory, a.grid, a.window, a.unet_width, a.levels, a.latent, a.hidden, a.head_hidden).to(device)
    params = list(model.parameters())
    opt = torch.optim.Adam(params, lr=1e-3, eps=1e-8)
    # Several input sets, rotated, so the timing is not of one cached batch.
    sets = [synthetic(a.batch, a.window + a.rollout_steps, a.particles, device) for _ in range(4)]
    if cuda:
        torch.cuda.empty_cache()  # the reserved peak then counts this run's pool alone
        torch.cuda.reset_peak_memory_stats()
    times = []
    for k in range(a.warmup + a.steps):
        frames, material, dt = sets[k % len(sets)]
        sync()
        t0 = time.perf_counter()
        opt.zero_grad(set_to_none=True)
        loss = sequence_loss(model, frames, material, dt, a.rollout_steps, a.teacher, a.noise)
        loss.backward()
        if a.clip > 0:
            clip_per_parameter(params, a.clip)
        opt.step()
        value = loss.item()  # the Rust loop reads the loss every step too
        sync()
        if k >= a.warmup:
            times.append(time.perf_counter() - t0)
        if not math.isfinite(value):
            raise RuntimeError(f"non-finite loss {value} at step {k}")
    times.sort()
    median = times[len(times) // 2]
    mib = 2**20
    peak = (torch.cuda.max_memory_allocated() / mib, torch.cuda.max_memory_reserved() / mib) if cuda else (float("nan"),) * 2
    return a.batch / median, median, peak, sum(q.numel() for q in params), value


def main():
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--memory", default="none,mingru,minlstm", help="comma list of none|mingru|minlstm|gru|lstm")
    p.add_argument("--precision", default="fp32", help="comma list of fp32|tf32 (matmuls and cuDNN convs)")
    p.add_argument("--batch", type=int, default=16)
    p.add_argument("--steps", type=int, default=30, help="timed optimizer steps")
    p.add_argument("--warmup", type=int, default=5, help="untimed optimizer steps first")
    p.add_argument("--grid", type=int, default=64)
    p.add_argument("--window", type=int, default=2, help="velocity frames of history T")
    p.add_argument("--rollout-steps", type=int, default=4, help="P")
    p.add_argument("--teacher", type=int, default=1)
    p.add_argument("--particles", type=int, default=2500)
    for flag, default in [("unet-width", 32), ("levels", 4), ("latent", 32), ("hidden", 32), ("head-hidden", 64)]:
        p.add_argument(f"--{flag}", type=int, default=default)  # GridConfig's sizes
    p.add_argument("--noise", type=float, default=0.0)
    p.add_argument("--clip", type=float, default=1.0)
    p.add_argument("--device", default="cuda")
    a = p.parse_args()
    device = torch.device(a.device)
    name = torch.cuda.get_device_name(device) if device.type == "cuda" else "cpu"
    print(f"torch {torch.__version__} on {name}; n = {a.grid}, T = {a.window}, P = {a.rollout_steps} "
          f"(teacher {a.teacher}), N = {a.particles}, {a.warmup} warm-up + {a.steps} timed steps", flush=True)
    for memory in a.memory.split(","):
        for prec in a.precision.split(","):
            if prec not in ("fp32", "tf32"):
                raise SystemExit(f"unknown precision {prec!r}")
            rate, median, peak, params, loss = bench(memory, a, prec == "tf32", device)
            print(f"torch grid {memory} {prec} batch {a.batch}: {rate:.1f} samples/s "
                  f"({median * 1e3:.1f} ms/step)  [params {params}, peak {peak[0]:.0f} MiB, "
                  f"reserved {peak[1]:.0f} MiB, "
                  f"loss {loss:.4g}]", flush=True)


if __name__ == "__main__":
    main()
