"""Which code made a run: the git commit of the checkout (``unknown`` outside a checkout) and the code
version, a digest of the package's source files that compute results (exact also in an uncommitted or
unpacked tree).

A run's identity is its config hash and, by default, its code version (``logger.identity`` of a run,
``identity`` of the report): :data:`IDENTITIES`.
"""

from __future__ import annotations

import functools
import hashlib
import subprocess
from pathlib import Path

_REPO = Path(__file__).resolve().parents[2]
_PACKAGE = Path(__file__).resolve().parents[1]

# subpackages that never change what a run computes (tables, figures, speed measurements): a change there
# is not a new code version
NOT_RESULT_CODE = ("report", "plots", "benchmarks")
# what makes two runs the same: the same config hash and code version (the default), or the same config hash
IDENTITIES = ("config_and_code", "config")
DEFAULT_IDENTITY = IDENTITIES[0]


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


@functools.lru_cache(maxsize=8)
def code_version(package: Path = _PACKAGE) -> str:
    """16 hex chars of the SHA-256 over the ``.py`` files of ``package`` outside :data:`NOT_RESULT_CODE`:
    each file's path (relative, in sorted order), its size and its bytes. Computed once per process."""
    digest = hashlib.sha256()
    for path in sorted(package.rglob("*.py")):
        rel = path.relative_to(package)
        if rel.parts[0] in NOT_RESULT_CODE:
            continue
        data = path.read_bytes()
        digest.update(f"{rel.as_posix()} {len(data)}\n".encode())
        digest.update(data)
    return digest.hexdigest()[:16]


def same_code(identity: str) -> bool:
    """Whether runs of another code version count as other runs under ``identity`` (one of :data:`IDENTITIES`)."""
    return identity == "config_and_code"
