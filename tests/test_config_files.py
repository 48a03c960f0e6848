"""The default configuration files: read from the checkout's configs/ or, in an installed
wheel, from the package mosaicmap_configs (the same files as package data)."""

from pathlib import Path

import pytest

import pipeline.config as config
from pipeline.errors import BadInput

REPO = Path(__file__).resolve().parent.parent


def test_defaults_come_from_the_checkout_configs():
    names = [Path(n).name for n, _ in config.default_files()]
    assert names == sorted(p.name for p in (REPO / "configs").glob("*.toml"))
    cfg = config.default_config()
    assert {"ingest", "register", "tracker", "diff", "export", "simulate"} <= set(cfg)


def test_defaults_come_from_the_installed_package_without_a_checkout(monkeypatch, tmp_path):
    pytest.importorskip("mosaicmap_configs", reason="the package is installed by `pip install (-e) .` (make test)")
    monkeypatch.setattr(config, "CONFIG_DIR", tmp_path / "configs")  # as in site-packages: no configs/ beside
    files = config.default_files()
    assert [n.split("/")[-1] for n, _ in files] == sorted(p.name for p in (REPO / "configs").glob("*.toml"))
    assert all(n.startswith("mosaicmap_configs/") for n, _ in files)
    assert config.default_config() == _checkout_defaults(monkeypatch)


def _checkout_defaults(monkeypatch) -> dict:
    monkeypatch.setattr(config, "CONFIG_DIR", REPO / "configs")
    return config.default_config()


def test_no_default_files_is_one_clear_error(monkeypatch, tmp_path):
    monkeypatch.setattr(config, "CONFIG_DIR", tmp_path / "configs")
    monkeypatch.setattr(config, "CONFIG_PACKAGE", "mosaicmap_no_such_package")
    with pytest.raises(BadInput, match="no default configuration files"):
        config.default_config()


def test_a_broken_default_file_names_itself(monkeypatch, tmp_path):
    (tmp_path / "floor.toml").write_text("[ingest\n")
    monkeypatch.setattr(config, "CONFIG_DIR", tmp_path)
    with pytest.raises(BadInput, match="floor.toml: not valid TOML"):
        config.default_config()
