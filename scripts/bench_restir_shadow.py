#!/usr/bin/env python
"""Benchmark suite `restir_shadow`: same as `torchir bench restir_shadow` (see torchir/bench/restir_shadow.py)."""
from torchir.bench.restir_shadow import main

if __name__ == "__main__":
    main()
