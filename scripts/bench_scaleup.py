#!/usr/bin/env python
"""Benchmark suite `scaleup`: same as `torchir bench scaleup` (see torchir/bench/scaleup.py)."""
from torchir.bench.scaleup import main

if __name__ == "__main__":
    main()
