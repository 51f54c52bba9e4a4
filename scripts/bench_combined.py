#!/usr/bin/env python
"""Benchmark suite `combined`: same as `torchir bench combined` (see torchir/bench/combined.py)."""
from torchir.bench.combined import main

if __name__ == "__main__":
    main()
