"""Which code made a run: the git commit of the checkout (``unknown`` outside a checkout)."""

from __future__ import annotations

import functools
import subprocess
from pathlib import Path

_REPO = Path(__file__).resolve().parents[2]


def _git(args: list[str], cwd: Path) -> str | None:
    try:
        out = subprocess.run(["git", *args], cwd=cwd, capture_output=True, text=True, timeout=10)
    except (OSError, subprocess.SubprocessError):
        return None
    return out.stdout.strip() if out.returncode == 0 else None


@functools.lru_cache(maxsize=8)
def git_info(repo: Path = _REPO) -> tuple[str, bool]:
    """(commit sha, dirty) of the checkout holding ``repo``; ``("unknown", False)`` without git.

    ``dirty`` is True when tracked files differ from the commit (untracked files are ignored).
    """
    sha = _git(["rev-parse", "HEAD"], repo)
    if not sha:
        return "unknown", False
    status = _git(["status", "--porcelain", "--untracked-files=no"], repo)
    return sha, bool(status)
