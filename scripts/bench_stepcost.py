#!/usr/bin/env python
"""Benchmark suite `stepcost`: same as `torchir bench stepcost` (see torchir/bench/stepcost.py)."""
from torchir.bench.stepcost import main

if __name__ == "__main__":
    main()
