#!/usr/bin/env python
"""Benchmark suite `denoiser`: same as `torchir bench denoiser` (see torchir/bench/denoiser.py)."""
from torchir.bench.denoiser import main

if __name__ == "__main__":
    main()
