#!/usr/bin/env python
"""Benchmark suite `restir_views`: same as `torchir bench restir_views` (see torchir/bench/restir_views.py)."""
from torchir.bench.restir_views import main

if __name__ == "__main__":
    main()
