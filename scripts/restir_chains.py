#!/usr/bin/env python
"""How close the persistent preset's chains get to the camera-sampling floor, at equal samples.

The fixed gradient problem of ``torchir bench restir`` (the L2 adjoint at the grey texture,
1 spp a step, the reference's own error removed in quadrature): the floor is extrapolated from
RIS over 256 and 1024 shadowed candidates (``e² = floor² + L / M``), then ``preset="persistent"``
runs with longer chains (burn-in passes, chain cap ``m_cap``). Errors are RMS over the steps.

    python scripts/restir_chains.py many_lights            # 128², 256 steps, oracles 256 steps (about 15 min)
    python scripts/restir_chains.py ajar_painting --steps 64
    python scripts/restir_chains.py ajar_painting --floor 0.00241 --steps 32 --chains 512:16384,2048:131072 --light-guide 0,0.5
    python scripts/restir_chains.py ajar_painting --floor 0.00241 --steps 32 --chains 8192:131072:4 --light-guide 0.5

Gradient paths: the samplers' default (``decorrelated`` since issue 39: a second resampling pass
a step); ``--grad-paths shared`` re-evaluates the image's paths, as the figures in docs/restir-measurements.md measured
before. At the fixed adjoint either is unbiased; the step times differ.
"""
from __future__ import annotations

import argparse
import time

import torchir  # before torch: it sets OMP_WAIT_POLICY

CHAINS = ((32, None), (32, 16384), (512, 16384), (2048, 131072))  # (burn_in, m_cap); None: the preset's


def main(argv=None) -> dict[str, float]:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0], formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("scene", choices=("ajar_painting", "many_lights", "oxalis_lite", "occluded_lights"))
    p.add_argument("--resolution", type=int, default=128)
    p.add_argument("--steps", type=int, default=256, help="steps of each persistent run")
    p.add_argument("--oracle-steps", type=int, default=256,
                   help="steps of each floor oracle (as the bench's; 32 put many_lights' floor 24%% higher)")
    p.add_argument("--ref-spp", type=int, default=16384)
    p.add_argument("--chains", default=None,
                   help="burn_in:m_cap pairs to run, comma-separated (m_cap 0: the preset's), each optionally "
                        ":candidates a step (default 16), e.g. 8192:131072:4; default: "
                        + ",".join(f"{b}:{m or 0}" for b, m in CHAINS) + ")")
    p.add_argument("--light-guide", default="0",
                   help="light_guide shares to run each chain with, comma-separated (0: off)")
    p.add_argument("--grad-paths", default="decorrelated", choices=("decorrelated", "shared"),
                   help="the samplers' gradient paths (default: decorrelated, the samplers' default)")
    p.add_argument("--floor", type=float, default=None,
                   help="the floor, if known (skips the two oracles; e.g. 0.00241 ajar_painting, 0.00178 many_lights at 128²)")
    a = p.parse_args(argv)

    from torchir.bench import restir
    from torchir.samplers import ReSTIRSampler

    torchir.backend.set_variant("auto")
    b = restir.parse_args(["--scenes", a.scene, "--resolution", str(a.resolution), "--ref-spp", str(a.ref_spp)])
    problem = restir.make_problem(a.scene, b)
    print(f"{a.scene} {a.resolution}²: reference relative SE {problem.ref_relative_se:.5f} ({problem.ref_seconds:.0f} s)", flush=True)

    def error(sampler, steps: int) -> tuple[float, float]:
        t0 = time.perf_counter()
        errors = [problem.step(sampler, 1, 1000 + i)[1] for i in range(steps)]
        return restir.error_beyond_reference(errors, problem.ref_relative_se)[0], time.perf_counter() - t0

    out = {}
    if a.floor is None:
        for m in (256, 1024):
            out[f"RIS {m}"] = error(ReSTIRSampler(problem.scene, preset="b2", candidates=m, grad_paths=a.grad_paths),
                                    a.oracle_steps)[0]
        floor = restir.camera_floor(out["RIS 256"], 256, out["RIS 1024"], 1024)
    else:
        floor = a.floor
    out["floor"] = floor
    source = "extrapolated" if a.floor is None else "given"
    print(f"| run | relative error | x floor | seconds |\n|---|---|---|---|\n| floor ({source}) | {floor:.5f} | 1 | |", flush=True)
    chains = CHAINS if a.chains is None else [tuple(int(v) for v in c.split(":")) for c in a.chains.split(",")]
    if any(len(c) not in (2, 3) for c in chains):
        p.error("--chains takes burn_in:m_cap or burn_in:m_cap:candidates, comma-separated")
    shares = [float(v) for v in a.light_guide.split(",")]
    for (burn_in, m_cap, *per_step), share in ((c, s) for c in chains for s in shares):
        candidates = per_step[0] if per_step else 16
        e, seconds = error(ReSTIRSampler(problem.scene, preset="persistent", candidates=candidates, burn_in=burn_in,
                                         m_cap=m_cap or None, light_guide=share, grad_paths=a.grad_paths), a.steps)
        name = (f"persistent, burn_in={burn_in}, m_cap={m_cap or 'default'}" + (f", candidates={candidates}" if per_step else "")
                + (f", light_guide={share:g}" if share else ""))
        out[name] = e
        print(f"| {name} | {e:.5f} | {e / floor if floor > 0 else float('inf'):.2f} | {seconds:.0f} |", flush=True)
    return out


if __name__ == "__main__":
    main()
