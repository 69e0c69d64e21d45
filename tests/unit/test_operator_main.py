"""The operator keeps no kopf diff base, which is safe only while no handler needs one.

kopf hands its create, update and resume handlers (and field handlers) a diff against
the last handled configuration; Roost stores none (``roost_operator.main.NoDiffBase``),
so every changing handler it registers must be a deletion handler, told by the deletion
mark. A new ``@kopf.on.update`` would silently see every event as a creation: this test
fails first.
"""

from __future__ import annotations

import kopf

from roost_operator.main import NoDiffBase, build_registry, configure
from roost_operator.settings import Settings


def test_every_changing_handler_is_a_deletion_handler() -> None:
    registry = build_registry(Settings())
    # kopf exposes no public listing of a registry's handlers; its changing registry is
    # where create/update/resume/field/delete handlers live.
    changing = registry._changing.get_all_handlers()
    assert changing, "the finalizer's cleanup handlers are expected here"
    assert {h.reason for h in changing} == {kopf.Reason.DELETE}
    assert all(h.field is None for h in changing)


def test_the_operator_stores_no_diff_base() -> None:
    settings = kopf.OperatorSettings()
    configure(settings, Settings())
    assert isinstance(settings.persistence.diffbase_storage, NoDiffBase)
