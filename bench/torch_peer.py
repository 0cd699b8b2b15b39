"""PyTorch eager peer of `fall-guard-lab bench`: the same EMP lite
network (docs/network.md, code: crates/runtime/src/model/), the same
batch-4 Adam step on one thread, reporting training samples/s.

Not part of the project's setup: run it from a throwaway venv with torch
installed (`pip install torch`, CPU wheel is enough):

    python bench/torch_peer.py [--steps 10] [--flush-denormal]

Like the Rust bench, a step is: building the input (standardised joints and
plan, low-passed frames), forward, BCE loss, backward, Adam (lr 1e-4, no
weight decay), on one fixed batch of uniform noise; the first step is warm-up.
The trajectory encoder chooses its periods per sample (the spec: a sample's
output never depends on its batch), so, as in the Rust code, each sample and
period runs its own Inception convolutions on its own grid.
"""

import argparse
import math
import time

import numpy as np
import torch
import torch.nn as nn
import torch.nn.functional as F

N, C, S, HORIZONS = 60, 25, 64, [15, 30, 45, 60]
K = len(HORIZONS)
L = N + HORIZONS[-1]
A = S // 4
PLAN_D, INC_DIM, NUM_KERNELS, TOP_K, NUM_TIMES = 32, 64, 3, 3, 2
NUM_TEMPORAL = 6
VISION = [8, 16, 32, 32]
TIME_POOL = [False, False, True, True]
D_MODEL = 1024
DROPOUT = 0.1


def dct_matrix(n):
    i = np.arange(n)[:, None]
    j = np.arange(n)[None, :]
    scale = np.sqrt(2.0 / n) / np.where(i == 0, np.sqrt(2.0), 1.0)
    return torch.tensor(scale * np.cos(np.pi / n * (j + 0.5) * i), dtype=torch.float32)


def lowpass_matrix(a, s):
    m = np.arange(2 * a)[:, None] / (2 * a) - np.arange(s)[None, :] / s
    acc = np.ones_like(m)
    for f in range(1, a):
        acc += 2.0 * np.cos(2.0 * np.pi * f * m)
    return torch.tensor(acc / s, dtype=torch.float32)


def dft_matrices(l):
    f = np.arange(l // 2 + 1)[:, None]
    n = np.arange(l)[None, :]
    ang = 2.0 * np.pi * ((f * n) % l) / l
    return (torch.tensor(np.cos(ang), dtype=torch.float32),
            torch.tensor(np.sin(ang), dtype=torch.float32))


class Motion(nn.Module):
    def __init__(self):
        super().__init__()
        self.register_buffer("d", dct_matrix(N))
        self.spatial_in = nn.Linear(C, C)
        self.norm_in = nn.LayerNorm(C)
        self.time = nn.ModuleList(nn.Linear(N, N) for _ in range(NUM_TEMPORAL))
        self.norm = nn.ModuleList(nn.LayerNorm(C) for _ in range(NUM_TEMPORAL))
        self.spatial_out = nn.Linear(C, C)
        self.norm_out = nn.LayerNorm(C)

    def forward(self, j):
        x = self.d @ j
        x = self.norm_in(self.spatial_in(x))
        for t, nrm in zip(self.time, self.norm):
            x = x + nrm(t(x.transpose(1, 2)).transpose(1, 2))
        x = self.norm_out(self.spatial_out(x))
        return (self.d.t() @ x).flatten(1)


class Inception2d(nn.Module):
    def __init__(self, cin, cout):
        super().__init__()
        self.branches = nn.ModuleList(
            nn.Conv2d(cin, cout, 2 * i + 1, padding=i) for i in range(NUM_KERNELS))

    def forward(self, x):
        return sum(b(x) for b in self.branches) / len(self.branches)


class Inception3d(nn.Module):
    def __init__(self, cin, cout):
        super().__init__()
        self.branches = nn.ModuleList(nn.Conv3d(cin, cout, k, padding=k // 2) for k in (1, 3))

    def forward(self, x):
        return sum(b(x) for b in self.branches) / len(self.branches)


class Plan(nn.Module):
    def __init__(self):
        super().__init__()
        self.embed = nn.Linear(C, PLAN_D)
        self.conv_in = nn.ModuleList(Inception2d(PLAN_D, INC_DIM) for _ in range(NUM_TIMES))
        self.conv_out = nn.ModuleList(Inception2d(INC_DIM, PLAN_D) for _ in range(NUM_TIMES))
        self.norm = nn.ModuleList(nn.LayerNorm(PLAN_D) for _ in range(NUM_TIMES))
        cos, sin = dft_matrices(L)
        self.register_buffer("cos_t", cos.t().contiguous())
        self.register_buffer("sin_t", sin.t().contiguous())

    def forward(self, plan):
        b = plan.shape[0]
        x = self.embed(plan)  # [B, L, d]
        d = x.shape[2]
        for ci, co, nrm in zip(self.conv_in, self.conv_out, self.norm):
            xt = x.transpose(1, 2)
            amp = ((xt @ self.cos_t) ** 2 + (xt @ self.sin_t) ** 2 + 1e-12).sqrt().mean(1)  # [B, F]
            host = amp.detach().numpy()
            outs = []
            for s in range(b):
                row = host[s]
                freqs = sorted(range(1, len(row)), key=lambda f: (-row[f], f))[:TOP_K]
                w = torch.softmax(amp[s, freqs], 0)
                acc = 0
                for i, f in enumerate(freqs):
                    p = math.ceil(L / f)
                    rows = math.ceil(L / p)
                    lp = rows * p
                    xs = x[s:s + 1]
                    if lp > L:
                        xs = torch.cat([xs, xs.new_zeros(1, lp - L, d)], 1)
                    grid = xs.reshape(1, rows, p, d).permute(0, 3, 1, 2)
                    y = co(F.gelu(ci(grid)))
                    y = y.permute(0, 2, 3, 1).reshape(1, lp, d)[:, :L]
                    acc = acc + y * w[i]
                outs.append(acc)
            x = nrm(torch.cat(outs, 0) + x)
        return x.flatten(1)


class Vision(nn.Module):
    def __init__(self):
        super().__init__()
        chans = [3] + VISION
        self.layers = nn.ModuleList(Inception3d(a, b) for a, b in zip(chans, chans[1:]))

    def forward(self, x):
        for layer, tp in zip(self.layers, TIME_POOL):
            x = F.relu(layer(x))
            x = F.max_pool3d(x, (2 if tp else 1, 2, 2))
        return x.flatten(1)


class Emp(nn.Module):
    def __init__(self):
        super().__init__()
        self.motion = Motion()
        self.plan = Plan()
        self.vision = Vision()
        t = N
        hw = 2 * A
        for tp in TIME_POOL:
            hw //= 2
            t = t // 2 if tp else t
        feats = N * C + L * PLAN_D + VISION[-1] * t * hw * hw
        self.hidden = nn.Linear(feats, D_MODEL)
        self.dropout = nn.Dropout(DROPOUT)
        self.out = nn.Linear(D_MODEL, K)

    def forward(self, joints, plan, frames):
        f = torch.cat([self.motion(joints), self.plan(plan), self.vision(frames)], 1)
        a = self.out(self.dropout(F.gelu(self.hidden(f))))
        return torch.cat([a[:, :1], F.softplus(a[:, 1:])], 1).cumsum(1)


def main():
    ap = argparse.ArgumentParser()
    ap.add_argument("--steps", type=int, default=10)
    ap.add_argument("--flush-denormal", action="store_true")
    args = ap.parse_args()
    torch.set_num_threads(1)
    torch.manual_seed(1)
    if args.flush_denormal:
        torch.set_flush_denormal(True)
    model = Emp()
    model.train()
    opt = torch.optim.Adam(model.parameters(), lr=1e-4, eps=1e-5)
    p = lowpass_matrix(A, S)
    rng = np.random.default_rng(0)
    # Uniform noise in [0, 1), like the Rust bench (another generator).
    joints = [rng.random(N * C, dtype=np.float32) for _ in range(4)]
    plan = [rng.random(L * C, dtype=np.float32) for _ in range(4)]
    frames = [rng.random(3 * N * S * S, dtype=np.float32) for _ in range(4)]
    labels = torch.tensor([[float((h + i) % 2) for h in range(K)] for i in range(4)])
    mean, std = 0.0, 1.0
    times = []
    for step in range(args.steps + 1):
        t0 = time.perf_counter()
        j = (torch.from_numpy(np.stack(joints)).reshape(4, N, C) - mean) / std
        pl = (torch.from_numpy(np.stack(plan)).reshape(4, L, C) - mean) / std
        fr = torch.from_numpy(np.stack(frames)).reshape(4, 3, N, S, S)
        fr = p @ fr @ p.t()  # low-pass + decimation, [4, 3, N, 2a, 2a]
        logits = model(j, pl, fr)
        loss = F.binary_cross_entropy_with_logits(logits, labels)
        opt.zero_grad(set_to_none=True)
        loss.backward()
        opt.step()
        if step > 0:
            times.append(time.perf_counter() - t0)
    total = sum(times)
    print(f"torch {torch.__version__}, 1 thread, {args.steps} steps: "
          f"{4 * args.steps / total:.1f} samples/s "
          f"(median step {1e3 * sorted(times)[len(times) // 2]:.0f} ms)")


if __name__ == "__main__":
    main()
