"""Where the third-party test data is: ``$LFCAM_DATA``, else ``../shared/data`` beside the
repository. It is read in place, never copied; tests that need it skip where it is absent."""

from __future__ import annotations

import os
from pathlib import Path

SHARED_DATA = Path(
    os.environ.get("LFCAM_DATA") or Path(__file__).resolve().parents[2] / "shared" / "data"
)
