#!/usr/bin/env python
"""Memory and recompilation soak: same as `torchir bench soak` (see torchir/bench/soak.py)."""
from torchir.bench.soak import main

if __name__ == "__main__":
    main()
