"""The fixture every test of Debian's real `blender` starts from."""
import pytest

from . import blender_chroot as bc


@pytest.fixture(scope="module")
def chroot():
    """The chroot's path, made (or reused) once per module, naming the Blender that runs in it;
    skipped only where this machine cannot make one (not root, no debootstrap)."""
    try:
        root = bc.ensure_chroot()
    except bc.ChrootUnavailable as exc:
        pytest.skip("Blender chroot unavailable: %s" % exc)
    print("e2e with " + bc.describe()["text"])
    return root
