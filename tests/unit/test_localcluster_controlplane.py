"""Choosing the control plane's datastore (etcd, or kine as in K3s), without starting it.

The control-plane suite itself runs on both (``pytest --datastore kine``); these pin the
parts that decide what is started and built: the component order, the refusal of an
unknown datastore, and a kine binary of another version counting as missing.
"""

from __future__ import annotations

from pathlib import Path

import pytest

from roost_localcluster import binaries
from roost_localcluster.controlplane import START_ORDER, Settings


def test_kine_takes_etcds_place_at_the_start() -> None:
    assert Settings().start_order == START_ORDER
    assert Settings(datastore="kine").start_order == ("kine", *START_ORDER[1:])


def test_an_unknown_datastore_is_refused() -> None:
    with pytest.raises(ValueError, match="datastore"):
        Settings(datastore="postgres")


def test_kine_of_another_version_is_missing(tmp_path: Path) -> None:
    for name in (*binaries.COMPONENTS, "kine"):
        (tmp_path / name).write_text("")
    names = Settings(datastore="kine").start_order
    assert binaries.missing(tmp_path, names) == ["kine"]  # no version stamp yet
    (tmp_path / "kine.version").write_text("v0.0.1\n")
    assert binaries.missing(tmp_path, names) == ["kine"]
    (tmp_path / "kine.version").write_text(binaries.kine_version() + "\n")
    assert binaries.missing(tmp_path, names) == []
    assert binaries.missing(tmp_path) == []  # the etcd plane never needs kine


def test_the_kine_pin_is_read_from_its_wrapper_module() -> None:
    assert binaries.kine_version().startswith("v")
