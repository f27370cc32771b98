"""Iso-Dream world models as TorchRL modules."""

import os as _os
import sys as _sys

__version__ = "0.1.0"

# PyTorch backs CPU tensors of 2 MB and more with transparent huge pages when THP_MEM_ALLOC_ENABLE=1
# (read once, at its first allocation, so only if torch is not imported yet: the console scripts and
# `python -m isodream_rl...` import this package first). A world-model update allocates and frees
# activations of ~10-100 MB many times; with 4 KB pages each fresh one costs a page fault per page
# (a 92 MB buffer: ~50-90 ms to first touch instead of ~10 ms), measured in docs/architecture.md "Speed".
# Set THP_MEM_ALLOC_ENABLE=0 to opt out.
if "torch" not in _sys.modules:
    _os.environ.setdefault("THP_MEM_ALLOC_ENABLE", "1")
