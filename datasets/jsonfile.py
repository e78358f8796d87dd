"""JSON files read with one clear line on failure (shared by stores, foreign checkpoints and results)."""

from __future__ import annotations

import json
from pathlib import Path
from typing import Any

from gpc.datasets.errors import DataError


def read_json(path: Path) -> Any:
    """JSON from ``path``; a missing or damaged file is named in one line."""
    try:
        return json.loads(Path(path).read_text())
    except OSError as exc:
        raise DataError(f"{path}: cannot be read ({exc.strerror or exc})") from None
    except ValueError as exc:
        raise DataError(f"{path}: not valid JSON ({str(exc).splitlines()[0][:120]})") from None
