"""``stacklevel`` for warnings that should point at the user's line, however deep the call."""
from __future__ import annotations

import os
import sys

import torch

_INTERNAL = (os.path.dirname(os.path.abspath(__file__)) + os.sep, os.path.dirname(torch.__file__) + os.sep)


def user_stacklevel() -> int:
    """The ``stacklevel`` for a ``warnings.warn`` made by the caller of this function: the first
    frame outside ``torchir/modules`` and torch (``nn.Module.__call__``), i.e. the user's call of
    a loss or denoiser, its module twin or its constructor."""
    frame, level = sys._getframe(1), 1
    while frame is not None and frame.f_code.co_filename.startswith(_INTERNAL):
        frame, level = frame.f_back, level + 1
    return level
