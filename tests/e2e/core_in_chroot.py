"""The core's tests on Debian's own Python and NumPy: the e2e chroot's `python3` (sid: Python 3.14,
NumPy 2.4), the interpreter that Debian's `blender` embeds. No bpy there, so only `-m core` runs.

    python -m tests.e2e.core_in_chroot [PYTEST ARGS]

The files git tracks (and untracked ones it would track) are copied into a work folder inside the
chroot and pytest runs there; the exit status is pytest's. A `-m` among the arguments is combined
with `core` (this interpreter has nothing else to run).
"""
import os
import subprocess
import sys

from . import blender_chroot as bc

PROBE = "import sys, numpy; print('Python', sys.version.split()[0], '| NumPy', numpy.__version__)"


def _marker(args):
    """(args without the caller's -m, the caller's marker expression or None)."""
    out, expr, it = [], None, iter(args)
    for a in it:
        if a in ("-m", "--markexpr"):
            expr = next(it, None)
        elif a.startswith("--markexpr="):
            expr = a.split("=", 1)[1]
        elif a.startswith("-m") and len(a) > 2:
            expr = a[2:]
        else:
            out.append(a)
    return out, expr


def main(argv):
    root = bc.ensure_chroot()
    work = bc.new_workdir(root)
    try:
        inside = bc.copy_sources(work, "src", keep=lambda n: not n.startswith("out/"))  # docs/: links
        args, expr = _marker(argv)
        mark = "core" if expr is None else f"core and ({expr})"
        env = {"PATH": "/usr/sbin:/usr/bin:/sbin:/bin", "HOME": "/root", "LANG": "C.UTF-8",
               "VPFFD_CORE_ONLY": "1"}
        for key in ("VPFFD_STRICT_SKIPS", "VPFFD_PASS", "CI"):
            if key in os.environ:
                env[key] = os.environ[key]
        probe = subprocess.run([bc._chroot_cmd(), root, "python3", "-c", PROBE], env=env,
                               capture_output=True, text=True)
        print(f"core_in_chroot: {os.path.basename(root)}: {probe.stdout.strip()}", file=sys.stderr)
        cmd = [bc._chroot_cmd(), root, "/bin/sh", "-c", 'cd "$0" && exec python3 -m pytest "$@"',
               inside, "-m", mark] + args
        return subprocess.run(cmd, env=env, stdin=subprocess.DEVNULL).returncode
    finally:
        bc.remove_workdir(work)


if __name__ == "__main__":
    sys.exit(main(sys.argv[1:]))
