#!/usr/bin/env python
"""Benchmark suite `restir`: same as `torchir bench restir` (see torchir/bench/restir.py)."""
from torchir.bench.restir import main

if __name__ == "__main__":
    main()
