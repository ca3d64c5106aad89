"""``GraphCache`` (physics/replay.py): the objects it holds for the keys it has seen.

A key names objects by address (a contact side subset, the indenter struct); if an object were freed while its key is
still known, a new object could be made at the same address, take the old key and be captured on its first use (see
the module's docstring). The CUDA path is exercised by the solver's replay tests (tests/test_physics_sparse_product.py);
this one checks the bookkeeping on any machine."""

from __future__ import annotations

import gc
import weakref
from types import SimpleNamespace

from transtac_sim.physics.replay import GraphCache


class _Subset:
    """Stands in for a contact side subset: an object named in a key by its address."""


def test_a_key_launched_once_holds_its_objects_until_cleared():
    cache = GraphCache("cpu")
    cache.device = SimpleNamespace(is_cuda=True)  # bookkeeping only: a key's first use launches; nothing is captured
    subset, launched = _Subset(), []
    alive = weakref.ref(subset)
    cache.run(("hessian", id(subset)), (subset,), lambda: launched.append("first"))
    del subset
    gc.collect()
    assert launched == ["first"] and alive() is not None  # its address cannot name another object while it is known
    cache.clear()
    gc.collect()
    assert alive() is None


def test_a_key_is_captured_on_its_second_use_and_replayed_after(monkeypatch):
    from transtac_sim.physics import replay

    class FakeCapture:  # stands in for wp.ScopedCapture: records that a capture ran
        def __init__(self, **kwargs):
            self.graph = object()

        def __enter__(self):
            return self

        def __exit__(self, *exc):
            return False

    replayed = []
    monkeypatch.setattr(replay.wp, "ScopedCapture", FakeCapture)
    monkeypatch.setattr(replay.wp, "capture_launch", lambda graph: replayed.append(graph))
    cache = GraphCache("cpu")
    cache.device = SimpleNamespace(is_cuda=True)
    subset, launched = _Subset(), []
    alive = weakref.ref(subset)
    key = ("hessian", id(subset))
    for _ in range(4):  # launched, captured (and launched from the graph), then replayed twice
        cache.run(key, (subset,), lambda: launched.append("launch"))
    assert launched == ["launch", "launch"] and cache.captures == 1 and len(replayed) == 3
    assert len(set(map(id, replayed))) == 1  # the one captured graph
    del subset
    gc.collect()
    assert alive() is not None  # held by the graph's entry
    cache.clear()
    gc.collect()
    assert alive() is None


def test_clear_by_name_drops_only_those_keys():
    cache = GraphCache("cpu")
    cache.device = SimpleNamespace(is_cuda=True)
    subset, other, launched = _Subset(), _Subset(), []
    alive, kept = weakref.ref(subset), weakref.ref(other)
    cache.run(("hessian", id(subset)), (subset,), lambda: launched.append("hessian"))
    cache.run(("energy", id(other)), (other,), lambda: launched.append("energy"))
    del subset, other
    cache.clear("hessian")
    gc.collect()
    assert alive() is None and kept() is not None  # the Hessian's key is gone, the energy's is still known
    cache.run(("hessian", 1), (), lambda: launched.append("hessian"))
    assert launched == ["hessian", "energy", "hessian"]
