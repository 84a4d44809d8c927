import os
import sys

import torch

# the shared MJCF snippets and helpers live in tests/models.py
sys.path.insert(0, os.path.dirname(__file__))

# The tests step tiny tensors (B <= 64) and are bound by per-op overhead; intra-op threads only add contention
# (measured on 2 shared cores: the B=64 spring ant step took 11 s with 2 threads vs 1.2 s with 1).
torch.set_num_threads(1)
