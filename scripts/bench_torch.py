#!/usr/bin/env python3
"""PyTorch side of `deocc bench model`: the same GL-DoT configuration written in PyTorch, timed on
the same shapes with the same thread count. A comparison script only, never on deocc's main path.

Usage: bench_torch.py CONFIG.json OUT.json   (CONFIG: the model config deocc serialises)
"""
import json
import math
import sys
import time

try:
    import torch
    import torch.nn as nn
    import torch.nn.functional as F
except ImportError as e:
    print(f"torch is not importable: {e}", file=sys.stderr)
    sys.exit(3)


def ln(x, eps=1e-6):
    return F.layer_norm(x, x.shape[-1:], eps=eps)


def modulate(x, shift, scale):
    return x * (1 + scale) + shift


def patchify(x, p):  # (B, H, W, C) -> (B, N, p*p*C)
    b, h, w, c = x.shape
    x = x.reshape(b, h // p, p, w // p, p, c).permute(0, 1, 3, 2, 4, 5)
    return x.reshape(b, (h // p) * (w // p), p * p * c)


def unpatchify(x, p, c):
    b, n, _ = x.shape
    g = int(math.isqrt(n))
    return x.reshape(b, g, g, p, p, c).permute(0, 1, 3, 2, 4, 5).reshape(b, g * p, g * p, c)


def sincos(g, d):
    q = d // 4
    omega = 1.0 / (10000 ** (torch.arange(q) / q))
    ys, xs = torch.meshgrid(torch.arange(g), torch.arange(g), indexing="ij")
    xs, ys = xs.reshape(-1, 1).float(), ys.reshape(-1, 1).float()
    return torch.cat([torch.sin(xs * omega), torch.cos(xs * omega), torch.sin(ys * omega), torch.cos(ys * omega)], 1)


class SelfAttn(nn.Module):
    def __init__(s, d, heads, kind):
        super().__init__()
        s.qkv, s.proj, s.h, s.kind = nn.Linear(d, 3 * d), nn.Linear(d, d), heads, kind

    def forward(s, x):
        b, n, d = x.shape
        q, k, v = s.qkv(x).reshape(b, n, 3, s.h, d // s.h).permute(2, 0, 3, 1, 4)
        if s.kind == "linear":
            q, k = F.relu(q), F.relu(k)
            v1 = F.pad(v, (0, 1), value=1.0)
            out = q @ (k.transpose(2, 3) @ v1)
            out = out[..., :-1] / (out[..., -1:] + 1e-6)
        else:
            out = torch.softmax(q @ k.transpose(2, 3) / math.sqrt(d // s.h), -1) @ v
        return s.proj(out.transpose(1, 2).reshape(b, n, d))


class CrossAttn(nn.Module):
    def __init__(s, d, heads):
        super().__init__()
        s.q, s.kv, s.proj, s.h = nn.Linear(d, d), nn.Linear(d, 2 * d), nn.Linear(d, d), heads

    def forward(s, x, c):
        b, n, d = x.shape
        m = c.shape[1]
        q = s.q(x).reshape(b, n, s.h, d // s.h).transpose(1, 2)
        k, v = s.kv(c).reshape(b, m, 2, s.h, d // s.h).permute(2, 0, 3, 1, 4)
        out = torch.softmax(q @ k.transpose(2, 3) / math.sqrt(d // s.h), -1) @ v
        return s.proj(out.transpose(1, 2).reshape(b, n, d))


class MixFFN(nn.Module):
    def __init__(s, d, h, grid):
        super().__init__()
        s.inv, s.point, s.h, s.grid = nn.Linear(d, 2 * h), nn.Linear(h, d), h, grid
        s.dw = nn.Conv2d(2 * h, 2 * h, 3, padding=1, groups=2 * h)

    def forward(s, x):
        b, n, _ = x.shape
        y = F.silu(s.inv(x)).reshape(b, s.grid, s.grid, 2 * s.h).permute(0, 3, 1, 2)
        y = s.dw(y).permute(0, 2, 3, 1).reshape(b, n, 2 * s.h)
        v, g = y.chunk(2, -1)
        return s.point(v * F.silu(g))


class Block(nn.Module):
    def __init__(s, cfg):
        super().__init__()
        d = cfg["width"]
        s.attn = SelfAttn(d, d // cfg["head_dim"], cfg["attention"])
        s.cross = CrossAttn(d, d // cfg["head_dim"])
        s.ffn = MixFFN(d, round(cfg["mlp_ratio"] * d), cfg["resolution"] // cfg["patch"])
        s.table = nn.Parameter(torch.randn(6, d) / d ** 0.5)

    def forward(s, x, c, tmod):
        sm, cm, gm, sf, cf, gf = (s.table[None] + tmod).chunk(6, 1)
        x = x + gm * s.attn(modulate(ln(x), sm, cm))
        x = x + s.cross(x, c)
        return x + gf * s.ffn(modulate(ln(x), sf, cf))


class EncBlock(nn.Module):
    def __init__(s, d, heads):
        super().__init__()
        s.w1, s.w2 = nn.Parameter(torch.ones(d)), nn.Parameter(torch.ones(d))
        s.attn = SelfAttn(d, heads, "softmax")
        s.fc1, s.fc2 = nn.Linear(d, 4 * d), nn.Linear(4 * d, d)

    def forward(s, x):
        x = x + s.attn(ln(x) * s.w1)
        return x + s.fc2(F.gelu(s.fc1(ln(x) * s.w2)))


class GlDot(nn.Module):
    def __init__(s, cfg):
        super().__init__()
        d, p = cfg["width"], cfg["patch"]
        s.cfg = cfg
        s.x_embed = nn.Linear(p * p * (cfg["target_channels"] + cfg["cond_channels"]), d)
        s.register_buffer("pos", sincos(cfg["resolution"] // p, d))
        s.t1, s.t2, s.tb = nn.Linear(256, d), nn.Linear(d, d), nn.Linear(d, 6 * d)
        s.blocks = nn.ModuleList([Block(cfg) for _ in range(cfg["depth"])])
        s.final_table = nn.Parameter(torch.randn(2, d) / d ** 0.5)
        s.final = nn.Linear(d, p * p * cfg["target_channels"])
        cp = cfg["cond_patch"]
        s.c_embed = nn.Linear(cp * cp * cfg["cond_channels"], d)
        s.register_buffer("c_pos", sincos(cfg["resolution"] // cp, d))
        s.c_blocks = nn.ModuleList([EncBlock(d, d // cfg["head_dim"]) for _ in range(cfg["cond_depth"])])

    def encode(s, cond):
        x = s.c_embed(patchify(cond, s.cfg["cond_patch"])) + s.c_pos
        for b in s.c_blocks:
            x = b(x)
        return ln(x)

    def forward(s, x_t, t, cond, tokens):
        cfg = s.cfg
        x = s.x_embed(patchify(torch.cat([x_t, cond], 3), cfg["patch"])) + s.pos
        half = 128
        freqs = torch.exp(-math.log(10000) * torch.arange(half) / half)
        args = (t[:, None] * 1000) * freqs[None]
        temb = s.t2(F.silu(s.t1(torch.cat([args.cos(), args.sin()], 1))))
        tmod = s.tb(F.silu(temb)).reshape(-1, 6, cfg["width"])
        for b in s.blocks:
            x = b(x, tokens, tmod)
        sh, sc = (s.final_table[None] + temb[:, None]).chunk(2, 1)
        return unpatchify(s.final(modulate(ln(x), sh, sc)), cfg["patch"], cfg["target_channels"])


def median_time(fn, reps, warm_ups=1):
    for _ in range(warm_ups):
        fn()
    ts = []
    for _ in range(reps):
        t0 = time.perf_counter()
        fn()
        ts.append(time.perf_counter() - t0)
    ts.sort()
    return ts[len(ts) // 2]


def main():
    cfg = json.load(open(sys.argv[1]))
    threads = int(cfg.get("threads", 2))
    torch.set_num_threads(threads)
    torch.manual_seed(0)
    res, tc, cc = cfg["resolution"], cfg["target_channels"], cfg["cond_channels"]
    out = {"torch_version": torch.__version__, "threads": threads}
    m = GlDot(cfg)
    out["parameters"] = sum(p.numel() for p in m.parameters())
    opt = torch.optim.AdamW(m.parameters(), lr=1e-4)

    def train_step(b=8):
        x0 = torch.randn(b, res, res, tc)
        cond = torch.randn(b, res, res, cc)
        toks = m.encode(torch.cat([cond, cond], 0))
        c = 0.5 * toks[:b] + 0.5 * toks[b:]
        t = torch.rand(b)
        eps = torch.randn_like(x0)
        xt = (1 - t)[:, None, None, None] * x0 + t[:, None, None, None] * eps
        loss = ((m(xt, t, cond, c) - (eps - x0)) ** 2).mean()
        opt.zero_grad()
        loss.backward()
        opt.step()

    out["train_step_batch_8_s"] = median_time(train_step, 9, warm_ups=3)

    @torch.no_grad()
    def forward(b=1):
        cond = torch.randn(b, res, res, cc)
        toks = m.encode(cond)
        m(torch.randn(b, res, res, tc), torch.full((b,), 0.5), cond, toks)

    @torch.no_grad()
    def complete(b, steps=4):
        cond = torch.randn(b, res, res, cc)
        toks = m.encode(cond)
        x = torch.randn(b, res, res, tc)
        grid = torch.linspace(1, 0, steps + 1)
        for i in range(steps):
            v = m(x, torch.full((b,), float(grid[i])), cond, toks)
            x = x + (grid[i + 1] - grid[i]) * v

    out["forward_batch_1_s"] = median_time(lambda: forward(1), 30)
    out["complete_4_steps_batch_1_s"] = median_time(lambda: complete(1), 5)
    out["complete_4_steps_batch_8_s"] = median_time(lambda: complete(8), 3)
    json.dump(out, open(sys.argv[2], "w"), indent=2)


if __name__ == "__main__":
    main()
