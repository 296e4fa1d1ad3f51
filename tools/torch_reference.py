"""PyTorch timing reference for `minflow bench train --device cuda` (docs/cuda.md).

The same network and loss as minflow's paper configuration (encoder 5 -> 256 -> 1250 with
ELU after both layers and mean pooling over the N particles, a two-layer minGRU / minLSTM /
GRU / LSTM core of width 1250 with dropout 0.1 and an ELU Linear on the last step, the global
decoder 1250 -> 2 N, semi-implicit Euler, MSE plus 0.1 x the density-map MSE on a 32 x 32
grid), trained with Adam on random inputs, so that burn's CUDA backend and PyTorch are timed
on the same GPU in one run. Written for this comparison from the equations in
src/model/*.rs and src/train/paper/loss.rs; it is not minflow's model and is not used to train.

    python3 tools/torch_reference.py --cores mingru,gru --batch 80 --window 2 --steps 30

prints one line per (core, precision): samples per second (median step time, after warm-up
steps), peak allocated GPU memory and the parameter count (to check against minflow's table).
"""

import argparse
import time

import torch
import torch.nn as nn
import torch.nn.functional as F


def g(x):
    return torch.where(x >= 0, x + 0.5, torch.sigmoid(x))


class MinGru(nn.Module):
    def __init__(self, d_in, w):
        super().__init__()
        self.z, self.h, self.out = nn.Linear(d_in, w), nn.Linear(d_in, w), nn.Linear(w, w)

    def forward(self, x):  # x [B, T, d]
        z, ht = torch.sigmoid(self.z(x)), g(self.h(x))
        h = torch.zeros_like(z[:, 0])
        outs = []
        for t in range(x.shape[1]):
            h = (1 - z[:, t]) * h + z[:, t] * ht[:, t]
            outs.append(h)
        return self.out(torch.stack(outs, 1))


class MinLstm(nn.Module):
    def __init__(self, d_in, w):
        super().__init__()
        self.f, self.i = nn.Linear(d_in, w), nn.Linear(d_in, w)
        self.h, self.out = nn.Linear(d_in, w), nn.Linear(w, w)

    def forward(self, x):
        f, i = torch.sigmoid(self.f(x)), torch.sigmoid(self.i(x))
        ht = g(self.h(x))
        fp, ip = f / (f + i), i / (f + i)
        h = torch.zeros_like(f[:, 0])
        outs = []
        for t in range(x.shape[1]):
            h = fp[:, t] * h + ip[:, t] * ht[:, t]
            outs.append(h)
        return self.out(torch.stack(outs, 1))


class Classic(nn.Module):
    def __init__(self, kind, d_in, w):
        super().__init__()
        self.rnn = (nn.GRU if kind == "gru" else nn.LSTM)(d_in, w, batch_first=True)

    def forward(self, x):
        return self.rnn(x)[0]


class Mlp(nn.Module):
    def __init__(self, d_in, w):
        super().__init__()
        self.l = nn.Linear(d_in, w)

    def forward(self, x):
        return F.elu(self.l(x))


def layer(kind, d_in, w):
    return {
        "mingru": lambda: MinGru(d_in, w),
        "minlstm": lambda: MinLstm(d_in, w),
        "gru": lambda: Classic("gru", d_in, w),
        "lstm": lambda: Classic("lstm", d_in, w),
        "mlp": lambda: Mlp(d_in, w),
    }[kind]()


class Model(nn.Module):
    def __init__(self, core, n, w=1250, hidden=256, layers=2):
        super().__init__()
        self.e1, self.e2 = nn.Linear(5, hidden), nn.Linear(hidden, w)
        self.layers = nn.ModuleList([layer(core, w, w) for _ in range(layers)])
        self.drop = nn.Dropout(0.1)
        self.mlp = nn.Linear(w, w)
        self.dec = nn.Linear(w, 2 * n)
        self.n = n

    def forward(self, x, dt):  # x [B, T, N, 5] scaled, identity scaling
        b, t, n, _ = x.shape
        z = F.elu(self.e2(F.elu(self.e1(x)))).mean(2)  # [B, T, W]
        for l in self.layers:
            z = self.drop(l(z))
        latent = F.elu(self.mlp(z[:, -1]))
        dv = self.dec(latent).view(b, n, 2)
        last = x[:, -1]
        v = last[..., 2:4] + dv
        pos = last[..., 0:2] + v * dt.view(b, 1, 1)
        return torch.cat([pos, v], -1)


def density(pos, grid=32):
    b, n, _ = pos.shape
    centres = torch.arange(grid, device=pos.device, dtype=pos.dtype) + 0.5
    tent = lambda c: torch.relu(1 - (c.unsqueeze(-1) * grid - centres).abs())  # [B, N, G]
    return tent(pos[..., 0]).transpose(1, 2) @ tent(pos[..., 1]) * (grid * grid / n)


def loss_fn(pred, target):
    mse = ((pred - target) ** 2).mean()
    dens = ((density(pred[..., :2]) - density(target[..., :2])) ** 2).mean()
    return mse + 0.1 * dens


def bench(core, batch, window, n, steps, warmup, tf32):
    torch.backends.cuda.matmul.allow_tf32 = tf32
    torch.backends.cudnn.allow_tf32 = tf32
    torch.manual_seed(0)
    dev = torch.device("cuda")
    model = Model(core, n).to(dev)
    opt = torch.optim.Adam(model.parameters(), lr=1e-3, eps=1e-8)
    params = sum(p.numel() for p in model.parameters())
    # Several input sets, rotated, so the timing is not of one cached batch.
    sets = [
        (
            torch.rand(batch, window, n, 5, device=dev),
            torch.rand(batch, n, 4, device=dev),
            torch.full((batch,), 0.016, device=dev),
        )
        for _ in range(4)
    ]
    torch.cuda.reset_peak_memory_stats()
    times = []
    for k in range(warmup + steps):
        x, y, dt = sets[k % len(sets)]
        torch.cuda.synchronize()
        t0 = time.perf_counter()
        opt.zero_grad(set_to_none=True)
        loss = loss_fn(model(x, dt), y)
        loss.backward()
        opt.step()
        loss.item()
        torch.cuda.synchronize()
        if k >= warmup:
            times.append(time.perf_counter() - t0)
    times.sort()
    median = times[len(times) // 2]
    peak = torch.cuda.max_memory_allocated() / 2**20
    return batch / median, median, peak, params


def main():
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--cores", default="mingru,gru,minlstm,lstm,mlp")
    p.add_argument("--batch", type=int, default=80)
    p.add_argument("--window", type=int, default=2)
    p.add_argument("--particles", type=int, default=2500)
    p.add_argument("--steps", type=int, default=30)
    p.add_argument("--warmup", type=int, default=5)
    p.add_argument("--precision", default="fp32,tf32", help="fp32 and/or tf32 matmuls")
    a = p.parse_args()
    print(f"torch {torch.__version__} on {torch.cuda.get_device_name()}, batch {a.batch}, "
          f"T = {a.window}, N = {a.particles}")
    print(f"{'core':<8} {'prec':<5} {'params':>10} {'ms/step':>8} {'samples/s':>10} {'peak MiB':>9}")
    for core in a.cores.split(","):
        for prec in a.precision.split(","):
            rate, median, peak, params = bench(
                core, a.batch, a.window, a.particles, a.steps, a.warmup, prec == "tf32"
            )
            print(f"{core:<8} {prec:<5} {params:>10} {median * 1e3:>8.1f} {rate:>10.0f} {peak:>9.0f}",
                  flush=True)


if __name__ == "__main__":
    main()
