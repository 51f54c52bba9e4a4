"""Quickstart: recover the Cornell box's wall colours from a synthetic target image.

The main job of the README until the Lightning trainer lands. It renders a target with the
true albedos at high spp, starts both coloured walls at grey, and runs Adam through
``torchir.functions.render``. It prints progress and writes, under ``--out``: target, initial
and final images (PNG), a loss / parameter-error plot and a metrics CSV.

    python scripts/quickstart.py --steps 60 --resolution 64
"""
from __future__ import annotations

import argparse
import csv
import time
from pathlib import Path

import torch

import torchir
from torchir.functions import render
from torchir.imageio import save_png

KEYS = ("red.reflectance.value", "green.reflectance.value")


def parse_args(argv: list[str] | None = None) -> argparse.Namespace:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--resolution", type=int, default=64)
    p.add_argument("--steps", type=int, default=60)
    p.add_argument("--spp", type=int, default=8)
    p.add_argument("--lr", type=float, default=0.05)
    p.add_argument("--out", type=Path, default=Path("results/quickstart"))
    return p.parse_args(argv)


def main(argv: list[str] | None = None) -> dict[str, float]:
    args = parse_args(argv)
    print(f"[quickstart] {torchir.backend.describe()}")
    scene = torchir.Scene.builtin("cbox", resolution=args.resolution)
    truth = {k: scene.get(k) for k in KEYS}
    target = render(scene, truth, spp=256, seed=2**31).detach()
    params = {k: torch.full((3,), 0.5, requires_grad=True) for k in KEYS}
    opt = torch.optim.Adam(params.values(), lr=args.lr)

    def param_error() -> float:
        with torch.no_grad():
            return float(sum(((params[k] - truth[k]) ** 2).sum() for k in KEYS).sqrt())

    with torch.no_grad():
        initial = render(scene, params, spp=64, seed=2**31 + 1)
    rows, start = [], time.perf_counter()
    for step in range(args.steps):
        opt.zero_grad()
        image = render(scene, params, spp=args.spp, seed=step)
        loss = ((image - target) ** 2).mean()
        loss.backward()
        opt.step()
        with torch.no_grad():
            for p in params.values():
                p.clamp_(0.0, 1.0)
        rows.append({"step": step, "loss": loss.item(), "param_error": param_error(), "seconds": time.perf_counter() - start})
        if step % max(args.steps // 10, 1) == 0 or step == args.steps - 1:
            print(f"[quickstart] step {step:4d}/{args.steps}  loss {rows[-1]['loss']:.3e}  parameter error {rows[-1]['param_error']:.4f}")

    with torch.no_grad():
        final = render(scene, params, spp=64, seed=2**31 + 2)
    args.out.mkdir(parents=True, exist_ok=True)
    for name, img in (("target", target), ("initial", initial), ("final", final)):
        save_png(args.out / f"{name}.png", img)
    with open(args.out / "metrics.csv", "w", newline="") as f:
        writer = csv.DictWriter(f, fieldnames=list(rows[0]))
        writer.writeheader()
        writer.writerows(rows)
    _plot(rows, args.out / "curves.png")
    summary = {
        "initial_param_error": float(sum(((0.5 - truth[k]) ** 2).sum() for k in KEYS).sqrt()),
        "final_param_error": rows[-1]["param_error"],
        "seconds": rows[-1]["seconds"],
    }
    print(
        f"[quickstart] parameter error {summary['initial_param_error']:.4f} -> {summary['final_param_error']:.4f} "
        f"in {summary['seconds']:.1f} s; recovered "
        + ", ".join(f"{k.split('.')[0]}={[round(v, 3) for v in params[k].tolist()]}" for k in KEYS)
        + f" (true: " + ", ".join(f"{k.split('.')[0]}={[round(v, 3) for v in truth[k].tolist()]}" for k in KEYS) + ")"
    )
    print(f"[quickstart] wrote {args.out}/(target|initial|final).png, curves.png, metrics.csv")
    return summary


def _plot(rows: list[dict[str, float]], path: Path) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, (a, b) = plt.subplots(1, 2, figsize=(9, 3.5))
    steps = [r["step"] for r in rows]
    a.semilogy(steps, [r["loss"] for r in rows])
    a.set(xlabel="step", ylabel="image loss (L2)", title="loss")
    b.semilogy(steps, [r["param_error"] for r in rows])
    b.set(xlabel="step", ylabel="||albedo - truth||", title="parameter error")
    fig.tight_layout()
    fig.savefig(path, dpi=100)
    plt.close(fig)


if __name__ == "__main__":
    main()
