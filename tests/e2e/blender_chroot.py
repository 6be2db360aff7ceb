"""Run Debian's real `blender` binary inside a debootstrap chroot: the newest Blender that Debian
packages (sid: 5.2.2 with Python 3.14 and NumPy 2.4, at the time of writing), or trixie's 4.3.2.

Standard library only. The chroot is made by `make_blender_chroot.sh` (about 70 s and ~1.2 GB the
first time, then reused). Which Debian suite: $VPFFD_DEBIAN_SUITE, by default sid; sid is Debian's
moving development suite and can fail to install any day, so when the default fails the tests fall
back to trixie and say so (`describe()` names the Blender that runs). No mounts are needed: `chroot DIR blender -b ...` works with the
chroot's empty /proc and /sys, so there is nothing to unmount after a run.

Every run gets a work folder inside the chroot (`DIR/tmp/vpffd-e2e-XXXX`, seen as
`/tmp/vpffd-e2e-XXXX` from inside). Blender starts with that folder as its working directory,
so relative paths in `args` resolve there, and the string `{work}` in `args` is replaced by its
path inside the chroot. Blender's user resources (`BLENDER_USER_RESOURCES`: preferences and
installed extensions) and HOME live in the work folder too, so successive runs sharing one work
folder share installed extensions, and nothing leaks between work folders.

    work = new_workdir()
    zip_path = build_extension(REPO_ROOT, work)          # or any extension zip on the host
    install_extension(zip_path, work)                     # persists in work's user resources
    rc, out, err, work = run_blender(["-b", "--python", "s.py"], files=["/host/s.py"], workdir=work)
    remove_workdir(work)

Runs that should see an installed extension must not pass `--factory-startup` (that skips the
saved preferences in which the extension is enabled), and scripts must not reset with
`wm.read_factory_settings` (use `wm.read_homefile(use_empty=True)`). Blender exits 0 after a
failing `--python` script unless `--python-exit-code 1` comes before it.
"""
import os
import shutil
import subprocess
import tempfile

HERE = os.path.dirname(os.path.abspath(__file__))
REPO_ROOT = os.path.dirname(os.path.dirname(HERE))
SCRIPT = os.path.join(HERE, "make_blender_chroot.sh")
ENV_VAR = "VPFFD_BLENDER_CHROOT"
SUITE_VAR = "VPFFD_DEBIAN_SUITE"
DEFAULT_SUITE = "sid"
FALLBACK_SUITE = "trixie"

# Exit codes of make_blender_chroot.sh that mean "this machine cannot make a chroot at all".
_EXIT_NOT_ROOT = 3
_EXIT_NO_DEBOOTSTRAP = 4


class ChrootUnavailable(RuntimeError):
    """The chroot cannot be made on this machine at all: not root, or no installable debootstrap."""


def _suite_dir(suite):
    return os.path.join(REPO_ROOT, ".cache", "blender-" + suite)


def _has_blender(root):
    return os.path.isfile(os.path.join(root, "usr", "bin", "blender"))


def _suites():
    """The suites to try, in order: the one asked for, or sid and then trixie."""
    asked = os.environ.get(SUITE_VAR)
    return [asked] if asked else [DEFAULT_SUITE, FALLBACK_SUITE]


def chroot_dir():
    """Where the chroot lives: $VPFFD_BLENDER_CHROOT, else <repo>/.cache/blender-SUITE for the
    first suite (see _suites) whose chroot holds a blender, else for the first suite."""
    path = os.environ.get(ENV_VAR)
    if not path:
        dirs = [_suite_dir(s) for s in _suites()]
        path = next((d for d in dirs if _has_blender(d)), dirs[0])
    return os.path.abspath(path)


def _chroot_cmd():
    return shutil.which("chroot") or shutil.which("chroot", path="/usr/sbin:/sbin:/usr/bin:/bin")


def ensure_chroot(timeout=1800):
    """Make (or reuse) the chroot and return its path.

    With neither $VPFFD_BLENDER_CHROOT nor $VPFFD_DEBIAN_SUITE set, sid is tried first and trixie
    when sid cannot be installed (printed, with sid's error). Raises ChrootUnavailable (a
    RuntimeError) when this machine cannot make one (not root, or debootstrap missing and not
    installable), RuntimeError for any other failure, with the tail of the script's log.
    """
    if os.name != "posix" or not hasattr(os, "geteuid"):
        raise ChrootUnavailable("a debootstrap chroot needs Linux")
    if os.geteuid() != 0:
        raise ChrootUnavailable("making and entering the Blender chroot needs root (euid is %d)"
                                % os.geteuid())
    if _chroot_cmd() is None:
        raise ChrootUnavailable("the 'chroot' command is not available")
    if os.environ.get(ENV_VAR):
        return _make(os.path.abspath(os.environ[ENV_VAR]), None, timeout)
    suites = _suites()
    for i, suite in enumerate(suites):
        try:
            return _make(_suite_dir(suite), suite, timeout)
        except ChrootUnavailable:
            raise
        except RuntimeError as exc:
            if i + 1 == len(suites):
                raise
            print("blender_chroot: Debian %s's blender could not be installed; falling back to %s.\n%s"
                  % (suite, suites[i + 1], exc))
    raise AssertionError("unreachable")


def _make(root, suite, timeout):
    env = dict(os.environ)
    if suite:
        env[SUITE_VAR] = suite
    try:
        proc = subprocess.run(["bash", SCRIPT, root], stdin=subprocess.DEVNULL,
                              stdout=subprocess.PIPE, stderr=subprocess.PIPE,
                              text=True, timeout=timeout, env=env)
    except subprocess.TimeoutExpired as exc:
        raise RuntimeError("make_blender_chroot.sh %s timed out after %ss" % (root, timeout)) from exc
    log = (proc.stdout + proc.stderr).strip()
    if proc.returncode in (_EXIT_NOT_ROOT, _EXIT_NO_DEBOOTSTRAP):
        raise ChrootUnavailable(log.splitlines()[-1] if log else "chroot unavailable")
    if proc.returncode != 0:
        tail = "\n".join(log.splitlines()[-40:])
        raise RuntimeError("could not make the Blender chroot at %s (exit %d):\n%s"
                           % (root, proc.returncode, tail))
    if log:
        print(log)
    return root


_described = {}


def describe():
    """'Blender X.Y.Z (Debian SUITE, Python A.B, NumPy C.D)' of the chroot in use (cached).
    Call after ensure_chroot()."""
    root = chroot_dir()
    if root not in _described:
        rc, out, err, work = run_blender(
            ["-b", "--factory-startup", "--python-expr",
             "import bpy, sys, numpy; print('VPFFD_DESCRIBE', bpy.app.version_string, '|', "
             "sys.version.split()[0], '|', numpy.__version__)"], timeout=300)
        remove_workdir(work)
        line = next((ln for ln in out.splitlines() if ln.startswith("VPFFD_DESCRIBE ")), None)
        if line is None:
            raise RuntimeError("the chroot's blender did not start (exit %s):\n%s" % (rc, err[-2000:]))
        version, py, npy = (p.strip() for p in line[len("VPFFD_DESCRIBE "):].split("|"))
        suite = os.path.basename(root)[len("blender-"):] if os.path.basename(root).startswith("blender-") else root
        _described[root] = {"version": version, "suite": suite, "python": py, "numpy": npy,
                            "text": "Blender %s (Debian %s, Python %s, NumPy %s)" % (version, suite, py, npy)}
    return _described[root]


def _inside(root, host_path):
    """Path as seen from inside the chroot of a host path below `root`."""
    rel = os.path.relpath(os.path.abspath(host_path), root)
    if rel.startswith(".."):
        raise ValueError("%s is not inside the chroot %s" % (host_path, root))
    return "/" + rel


def new_workdir(root=None):
    """A fresh work folder inside the chroot; returns its host path."""
    root = root or chroot_dir()
    tmp = os.path.join(root, "tmp")
    os.makedirs(tmp, exist_ok=True)
    work = tempfile.mkdtemp(prefix="vpffd-e2e-", dir=tmp)
    os.chmod(work, 0o755)
    for sub in ("user_resources", "home"):
        os.makedirs(os.path.join(work, sub), exist_ok=True)
    return work


def remove_workdir(work):
    """Delete a work folder made by new_workdir (host path)."""
    if work and os.path.basename(work).startswith("vpffd-e2e-"):
        shutil.rmtree(work, ignore_errors=True)


def copy_files(files, work):
    """Copy host files into the work folder. `files`: iterable of paths (kept by basename) or a
    mapping {name inside the work folder: host path}. Returns the host paths of the copies."""
    if not files:
        return []
    items = files.items() if hasattr(files, "items") else ((os.path.basename(p), p) for p in files)
    out = []
    for name, src in items:
        dst = os.path.join(work, name)
        os.makedirs(os.path.dirname(dst), exist_ok=True)
        shutil.copy2(src, dst)
        out.append(dst)
    return out


def run_blender(args, files=None, timeout=600, workdir=None, env=None):
    """Run `chroot DIR blender ARGS` (cwd: the work folder) and return
    (returncode, stdout, stderr, host path of the work folder).

    `files` are copied into the work folder first (see copy_files). `{work}` in `args` becomes
    the work folder's path inside the chroot. `env` adds variables to the clean environment
    (PATH, HOME, LANG, BLENDER_USER_RESOURCES) the binary gets; nothing from the host's
    environment (venv, PYTHONPATH, ...) leaks in. The work folder is kept: read outputs from
    it, then remove_workdir(). On timeout returncode is None and stderr says so.
    """
    root = chroot_dir()
    if not os.access(os.path.join(root, "usr", "bin", "blender"), os.X_OK):
        raise RuntimeError("no blender in %s; call ensure_chroot() first" % root)
    work = workdir or new_workdir(root)
    copy_files(files, work)
    inside = _inside(root, work)
    full_env = {
        "PATH": "/usr/sbin:/usr/bin:/sbin:/bin",
        "HOME": inside + "/home",
        "LANG": "C.UTF-8",
        "BLENDER_USER_RESOURCES": inside + "/user_resources",
    }
    full_env.update(env or {})
    args = [str(a).replace("{work}", inside) for a in args]
    # chroot(8) starts the command in /, so change into the work folder with a tiny shell.
    cmd = [_chroot_cmd(), root, "/bin/sh", "-c", 'cd "$0" && exec blender "$@"', inside] + args
    try:
        proc = subprocess.run(cmd, env=full_env, stdin=subprocess.DEVNULL,
                              stdout=subprocess.PIPE, stderr=subprocess.PIPE,
                              text=True, errors="replace", timeout=timeout)
    except subprocess.TimeoutExpired as exc:
        out = exc.stdout.decode(errors="replace") if isinstance(exc.stdout, bytes) else (exc.stdout or "")
        err = exc.stderr.decode(errors="replace") if isinstance(exc.stderr, bytes) else (exc.stderr or "")
        return None, out, err + "\n[blender_chroot] timed out after %ss" % timeout, work
    return proc.returncode, proc.stdout, proc.stderr, work


def copy_sources(workdir, into, keep=None, source_dir=REPO_ROOT):
    """Copy the source tree's files (those git tracks or would track, else the whole tree) whose
    relative name passes `keep` (all by default) into workdir/into/. Returns that folder's path
    as seen from inside the chroot."""
    names = [n for n in _source_files(source_dir) if keep is None or keep(n)]
    dest = os.path.join(workdir, into)
    copy_files({n: os.path.join(source_dir, n) for n in names}, dest)
    return _inside(chroot_dir(), dest)


def build_extension(source_dir, workdir, timeout=300):
    """Build the extension zip from `source_dir` (default: the files git tracks or would track,
    else the whole tree) with the chroot's `blender --command extension build`, which applies the
    manifest's [build] excludes. Returns the zip's host path (in workdir/ext_build/)."""
    copy_sources(workdir, "ext_src", source_dir=source_dir)
    os.makedirs(os.path.join(workdir, "ext_build"), exist_ok=True)
    rc, out, err, _ = run_blender(
        ["--command", "extension", "build", "--source-dir", "{work}/ext_src",
         "--output-dir", "{work}/ext_build"], workdir=workdir, timeout=timeout)
    outdir = os.path.join(workdir, "ext_build")
    zips = sorted(f for f in os.listdir(outdir) if f.endswith(".zip")) if os.path.isdir(outdir) else []
    if rc != 0 or not zips:
        raise RuntimeError("extension build failed (exit %s):\n%s\n%s" % (rc, out[-3000:], err[-3000:]))
    return os.path.join(outdir, zips[-1])


def _source_files(source_dir):
    skip_dirs = {".git", ".venv", ".cache", "__pycache__", ".pytest_cache", ".hypothesis"}
    try:
        out = subprocess.run(["git", "-C", source_dir, "ls-files", "-co", "--exclude-standard", "-z"],
                             stdout=subprocess.PIPE, stderr=subprocess.DEVNULL, check=True).stdout
        names = [n for n in out.decode().split("\0") if n]
    except (OSError, subprocess.CalledProcessError):
        names = []
        for dirpath, dirnames, filenames in os.walk(source_dir):
            dirnames[:] = [d for d in dirnames if d not in skip_dirs]
            names += [os.path.relpath(os.path.join(dirpath, f), source_dir) for f in filenames]
    return [n for n in names
            if not set(n.split("/")) & skip_dirs and os.path.isfile(os.path.join(source_dir, n))]


def install_extension(zip_path, workdir, repo="user_default", timeout=300):
    """Install and enable an extension zip (host path) in the work folder's user resources with
    `blender -b --command extension install-file -r REPO -e ZIP` (Blender 4.3.2 saves the
    preferences with the extension enabled, so later runs in this work folder load it unless they
    pass --factory-startup). Returns the (rc, stdout, stderr) of that run; raises RuntimeError if
    it failed."""
    name = os.path.basename(zip_path)
    copy_files({"ext_install/" + name: zip_path}, workdir)
    rc, out, err, _ = run_blender(
        ["-b", "--factory-startup", "--command", "extension", "install-file", "-r", repo, "-e",
         "{work}/ext_install/" + name], workdir=workdir, timeout=timeout)
    if rc != 0 or "STATUS Installed" not in out + err:
        raise RuntimeError("extension install of %s failed (exit %s):\n%s\n%s"
                           % (name, rc, out[-3000:], err[-3000:]))
    return rc, out, err
