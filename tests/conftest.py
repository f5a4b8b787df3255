"""Shared fixtures: a tiny generated data set (made once per test session) and ../shared paths; tests marked
``gpu`` skip themselves where there is no CUDA device."""

from __future__ import annotations

import os
from pathlib import Path

import pytest

REPO = Path(__file__).resolve().parents[1]
SHARED = REPO.parent / "shared"

os.environ.setdefault("OMP_NUM_THREADS", "2")


def pytest_collection_modifyitems(config: pytest.Config, items: list[pytest.Item]) -> None:
    """Tests marked ``gpu`` are skipped, saying why, where torch sees no CUDA device."""
    marked = [item for item in items if item.get_closest_marker("gpu") is not None]
    if not marked:
        return
    import torch

    if torch.cuda.is_available():
        return
    skip = pytest.mark.skip(reason="needs a CUDA GPU (torch.cuda.is_available() is false here)")
    for item in marked:
        item.add_marker(skip)


def shared_path(*parts: str) -> Path:
    """A path under ../shared, skipping the test cleanly when it is absent."""
    p = SHARED.joinpath(*parts)
    if not p.exists():
        pytest.skip(f"{p} is not available (../shared sits beside the checkout only in CI and dev)")
    return p


def compose(config_name: str, overrides: list[str]):
    """Compose a config from the repository's conf/ as the entry points do."""
    from hydra import compose as hydra_compose
    from hydra import initialize_config_dir

    with initialize_config_dir(config_dir=str(REPO / "conf"), version_base="1.3"):
        return hydra_compose(config_name=config_name, overrides=overrides)


def tiny_data_cfg(root: Path, *extra: str) -> dict:
    from omegaconf import OmegaConf

    cfg = compose("prepare", ["profile=tiny", f"data.root={root}", "data.workers=1", *extra])
    return OmegaConf.to_container(cfg.data, resolve=True)


@pytest.fixture(scope="session")
def tiny_root(tmp_path_factory) -> Path:
    """The `tiny` profile's generated data set, made once for the whole test session."""
    from pcrcg.data.materialise import prepare_dataset

    root = tmp_path_factory.mktemp("data") / "synthmatch-tiny"
    return prepare_dataset(tiny_data_cfg(root), seed=0, log=lambda m: None)
