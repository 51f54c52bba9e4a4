#!/usr/bin/env python
"""Benchmark suite `adaptive`: same as `torchir bench adaptive` (see torchir/bench/adaptive.py)."""
from torchir.bench.adaptive import main

if __name__ == "__main__":
    main()
