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
