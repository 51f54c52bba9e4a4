#!/usr/bin/env python
"""Benchmark suite `loi`: same as `torchir bench loi` (see torchir/bench/loi.py)."""
from torchir.bench.loi import main

if __name__ == "__main__":
    main()
