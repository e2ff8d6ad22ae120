"""TorchScript without torch's deprecation warnings: still the bundle's format (CONTRACT.md), ours to act on, not the user's."""
from __future__ import annotations

import contextlib
import warnings
from typing import Iterator

# torch 2.13 says so in a DeprecationWarning, 2.14 in a FutureWarning, which Python shows every user
DEPRECATED = r"`torch\.jit\.\w+` is deprecated"


@contextlib.contextmanager
def quiet_torchscript() -> Iterator[None]:
    """Hide torch's deprecation of ``torch.jit`` inside: two lines on every command's stderr would bury its one-line error."""
    with warnings.catch_warnings():
        warnings.filterwarnings("ignore", message=DEPRECATED)
        yield
