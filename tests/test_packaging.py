"""What `pip install gpc` builds holds every module of the checkout, under the one `gpc.` namespace.

pyproject.toml lists the packages by hand (the user's folders map onto `gpc.*`), so a new folder left off the list is
missing from a regular install while every editable checkout still imports it: the draw task and the baselines once
were. The full install beside Hugging Face's `datasets` is test_install's (make test-extended).
"""

from __future__ import annotations

import shutil
import subprocess
import sys
import zipfile
from pathlib import Path

import pytest
import tomllib

ROOT = Path(__file__).resolve().parents[1]


def tracked_modules() -> set[str]:
    """The installed names of the checkout's tracked modules (`models/ladi/module.py` -> `gpc/models/ladi/module.py`)."""
    tool = tomllib.loads((ROOT / "pyproject.toml").read_text())["tool"]["setuptools"]
    roots = {folder: name.replace(".", "/") for name, folder in tool["package-dir"].items()}
    files = subprocess.run(["git", "ls-files", *roots], cwd=ROOT, capture_output=True, text=True, check=True).stdout.split()
    out = set()
    for name in (f for f in files if f.endswith(".py")):
        top, _, rest = name.partition("/")
        out.add(f"{roots[top]}/{rest}")
    return out


def copy_project(source: Path) -> Path:
    """The project's files (tracked and not ignored) copied to ``source``: a build in the checkout would leave build/."""
    listing = ["git", "ls-files", "-z", "--cached", "--others", "--exclude-standard"]
    for name in filter(None, (f.decode() for f in subprocess.run(listing, cwd=ROOT, capture_output=True, check=True).stdout.split(b"\0"))):
        if (ROOT / name).is_file():
            (source / name).parent.mkdir(parents=True, exist_ok=True)
            shutil.copy2(ROOT / name, source / name)
    return source


@pytest.mark.skipif(not (ROOT / ".git").exists(), reason="needs the git checkout")
def test_the_wheel_holds_every_tracked_module(tmp_path):
    source = copy_project(tmp_path / "source")
    done = subprocess.run([sys.executable, "-m", "pip", "wheel", "-q", "--no-deps", "--no-build-isolation", str(source),
                           "-w", str(tmp_path / "wheel")], capture_output=True, text=True, timeout=300)
    assert done.returncode == 0, done.stderr[-2000:]
    (wheel,) = (tmp_path / "wheel").glob("gpc-*.whl")
    packed = {n for n in zipfile.ZipFile(wheel).namelist() if n.endswith(".py")}
    assert "gpc/tasks/draw/env.py" in tracked_modules()  # the listing reads the folders it should
    assert sorted(tracked_modules() - packed) == []
    assert not {n for n in packed if not n.startswith("gpc/")}  # nothing installs a top-level `models` or `tasks`
