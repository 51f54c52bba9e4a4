#!/usr/bin/env python
"""Overhead of torchir over a native Mitsuba loop: ``torchir bench overhead`` (see torchir/bench/overhead.py)."""
from torchir.bench.overhead import main

if __name__ == "__main__":
    main()
