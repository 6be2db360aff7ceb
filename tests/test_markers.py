"""Every test carries a layer marker (registered in pytest.ini), so that `./dev test -m LAYER`
runs one layer alone."""
import pytest

pytestmark = pytest.mark.core

LAYERS = {"core", "blender", "gpu", "fuzz", "e2e", "gui"}


def test_every_collected_test_has_a_layer(request):
    session = request.session
    unmarked = [item.nodeid for item in session.items
                if not LAYERS & {m.name for m in item.iter_markers()}]
    assert not unmarked, unmarked
