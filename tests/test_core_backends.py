"""The registry of backends (`vpffd_addon/backends.py`): the user's preference becomes one backend
and a reason, a backend that cannot do a solve's options (or is not available) is passed over
with its reason, and the `Solution` names the backend whose steps ran."""
import dataclasses

import numpy as np
import pytest

import vpffd_addon as vp
from vpffd_addon import backends
from vpffd_addon.steps import NumpySteps

pytestmark = pytest.mark.core


def _lattice_problem():
    lat = vp.Lattice((3, 3, 3), bounds=((-1,) * 3, (1,) * 3))
    v, t = vp.icosphere(2, 0.7)
    P = lat.rest_points.copy()
    P[:, 2] *= 0.7
    return vp.bind(lat, v, t, use_compiled=False), P


class _CountingSteps(NumpySteps):
    """NumPy's steps under another backend's name (a second backend with steps of its own)."""
    backend = "GPU"


@pytest.fixture
def gpu_entry():
    """A lattice-only, axes-only backend registered as GPU, as the Blender layer registers its
    compute shaders; unregistered afterwards."""
    entry = backends.Backend("GPU", "GPU", "GPU", frozenset({"lattice", "plain_measure"}),
                             steps=_CountingSteps)
    backends.register(entry)
    yield entry
    backends.unregister("GPU")
    assert backends.get("GPU") is None


def test_numpy_is_the_reference_and_cpu_falls_back_to_it():
    b, P = _lattice_problem()
    assert "NUMPY" in backends.registered() and "COMPILED" in backends.registered()
    chosen, why = backends.choose("NUMPY", b, {"axes": "XYZ"})
    assert chosen is backends.NUMPY and "reference" in why
    chosen_cpu, why = backends.choose("CPU", b, {"axes": "XYZ"})
    assert why == "CPU chosen" and chosen_cpu.name == ("COMPILED" if vp.compiled.ready() else "NUMPY")
    cage = vp.box_cage((1, 1, 1))
    v, t = vp.icosphere(1, 0.5)
    assert backends.usable(backends.COMPILED, "CPU", vp.bind(cage, v, t, depth=0), {}) == \
        (False, "cages solve with NumPy")
    sol = b.solve(P, steps=chosen.steps)
    assert sol.backend == "NUMPY"


def test_gpu_without_a_registered_gpu_backend_solves_on_the_cpu_and_says_why():
    b, _ = _lattice_problem()
    for pref in ("GPU", "AUTO", "gpu"):
        chosen, why = backends.choose(pref, b, {"axes": "XYZ"})
        assert chosen.device == "CPU" and "not registered" in why


def test_a_registered_backend_is_chosen_where_its_capabilities_reach(gpu_entry):
    b, P = _lattice_problem()
    chosen, _ = backends.choose("GPU", b, {"axes": "XYZ"})
    assert chosen is gpu_entry
    assert b.solve(P, steps=chosen.steps).backend == "GPU"
    assert backends.choose("CPU", b, {"axes": "XYZ"})[0].device == "CPU"
    for options, missing in (({"axes": "XYZ", "islands": True}, "islands"),
                             ({"axes": "", "directions": np.eye(3)[:1]}, "directions")):
        chosen, why = backends.choose("GPU", b, options)
        assert chosen.device == "CPU" and missing in why, why
    cage = vp.box_cage((1, 1, 1))
    v, t = vp.icosphere(1, 0.5)
    chosen, why = backends.choose("AUTO", vp.bind(cage, v, t, depth=0), {"axes": "XYZ"})
    assert chosen is backends.NUMPY and "cage" in why


def test_an_unavailable_or_refusing_backend_is_passed_over_with_its_words(gpu_entry):
    b, _ = _lattice_problem()
    backends.register(dataclasses.replace(gpu_entry, available=lambda: (False, "no GPU here")))
    assert backends.choose("GPU", b, {"axes": "XYZ"}) == (backends.NUMPY, "no GPU here")
    backends.register(dataclasses.replace(
        gpu_entry, accepts=lambda pref, binding, options, fresh: (pref != "AUTO" or not fresh, "just bound")))
    assert backends.choose("AUTO", b, {"axes": "XYZ"}, fresh=True) == (backends.NUMPY, "just bound")
    assert backends.choose("GPU", b, {"axes": "XYZ"}, fresh=True)[0].name == "GPU"
