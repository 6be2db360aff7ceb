"""`./dev package`: the packages users install, built with Blender's own extension builder, and
the index that makes `dist/` an extensions repository a studio serves over HTTP or as files.

    ./dev package                  # dist/: one package per platform with numba's wheels, a
                                   # NumPy-only one for each platform (or Blender before 5.1 on
                                   # Windows on ARM) numba has none for, index.json and
                                   # index.html; dist/universal/: a NumPy-only package for any
                                   # platform, to install from disk
    ./dev package --platform linux-x64 --python 3.13   # only what a test needs
    ./dev package --lock           # download every wheel once and write release/wheels.lock

The compiled kernels run on numba (with llvmlite), bundled as the unmodified wheels PyPI serves,
under ./wheels/ of the package and listed in its manifest (Blender's manual, "Extensions > Python
Wheels"); Blender installs only the wheels that match its Python. The committed manifest lists no
wheels, so building from a fresh clone (the README's install, every test) needs no download.

Every wheel is pinned by version and checked against its SHA-256 in `release/wheels.lock`
before it is packed. Downloads are kept in `.cache/wheels/` (git-ignored); each build stages its
source in a folder of its own under `build/package/` and the packages go to `dist/` (both
git-ignored).

The repository's index is written by Blender's own `extension server-generate` over every package
in the output folder, so that folder holds exactly one version of VP-FFD, with one package per
platform: Blender lists the last of several matching entries but installs the first, so older
versions, or a package for any platform beside the platform ones, would make what a user gets
depend on the order of the files. The any-platform package therefore lies in a subfolder, which
the index does not read.
"""
import argparse
import contextlib
import hashlib
import os
import re
import shutil
import subprocess
import sys
import tempfile
import tomllib
import zipfile

HERE = os.path.dirname(os.path.abspath(__file__))
ROOT = os.path.dirname(HERE)
sys.path.insert(0, ROOT)

from tests import extension_harness as eh  # noqa: E402  (Blender's builder, through bpy)

PINS = ("numba==0.68.1", "llvmlite==0.50.0")
#: Blender's platform names -> (pip platform tag, Python versions numba 0.68.1 has wheels for).
#: No macos-x64 wheels exist for it: that platform gets a NumPy-only package.
PLATFORMS = {
    "linux-x64": ("manylinux_2_28_x86_64", ("3.11", "3.13", "3.14")),
    "windows-x64": ("win_amd64", ("3.11", "3.13", "3.14")),
    "macos-arm64": ("macosx_12_0_arm64", ("3.11", "3.13", "3.14")),
    "windows-arm64": ("win_arm64", ("3.13",)),
}
#: Blender platforms with no numba wheels above (Intel Macs; ARM Linux, where Debian builds Blender):
#: each gets a NumPy-only package in the repository.
NUMPY_ONLY = ("macos-x64", "linux-arm64")
#: Official Blender builds embed Python 3.11 up to 5.0 and 3.13 from this version on. A platform
#: whose numba wheels lack 3.11 (Windows on ARM) gets its numba package from this version on and a
#: NumPy-only package for the Blender versions before it.
PYTHON_313_FROM = "5.1.0"
#: Subfolder of the output for the NumPy-only package without platforms (any platform, any Python).
UNIVERSAL = "universal"
LOCK = os.path.join(HERE, "wheels.lock")
CACHE = os.path.join(ROOT, ".cache", "wheels")
BUILD = os.path.join(ROOT, "build", "package")
DIST = os.path.join(ROOT, "dist")


class PackageError(RuntimeError):
    """A wheel could not be fetched or checked, or Blender's builder refused the package."""


def read_lock(path=LOCK):
    """{(platform, python): [(file name, sha256), ...]} from the lock file."""
    out = {}
    with open(path) as fh:
        for line in fh:
            line = line.split("#", 1)[0].strip()
            if line:
                platform, python, name, digest = line.split()
                out.setdefault((platform, python), []).append((name, digest))
    return out


def sha256(path):
    h = hashlib.sha256()
    with open(path, "rb") as fh:
        for chunk in iter(lambda: fh.read(1 << 20), b""):
            h.update(chunk)
    return h.hexdigest()


def download(platform, python, dest=CACHE):
    """Fetch the pinned wheels for one platform and Python version into `dest`; their paths."""
    tag, _ = PLATFORMS[platform]
    target = os.path.join(dest, f"{platform}-{python}")
    os.makedirs(target, exist_ok=True)
    cmd = [sys.executable, "-m", "pip", "download", *PINS, "--no-deps", "--only-binary=:all:",
           "--python-version", python, "--platform", tag, "--dest", target, "--quiet",
           "--disable-pip-version-check"]
    proc = subprocess.run(cmd, capture_output=True, text=True)
    if proc.returncode != 0:
        raise PackageError(f"pip could not download {' '.join(PINS)} for {platform}, Python "
                           f"{python}:\n{proc.stderr[-2000:]}")
    prefixes = tuple(pin.replace("==", "-") + "-" for pin in PINS)     # numba-0.68.1-...whl
    names = sorted(n for n in os.listdir(target) if n.endswith(".whl") and n.startswith(prefixes))
    return [os.path.join(target, n) for n in names]


@contextlib.contextmanager
def _only_one(folder):
    """Hold an exclusive lock on `folder` (its `.lock` file) while inside: the test passes of
    `./dev test` build packages side by side, and two downloads into one cache folder would write
    the same files at once. Where `fcntl` is missing (Windows) nothing is locked."""
    os.makedirs(folder, exist_ok=True)
    try:
        import fcntl
    except ImportError:
        yield
        return
    with open(os.path.join(folder, ".lock"), "w") as fh:
        fcntl.flock(fh, fcntl.LOCK_EX)
        try:
            yield
        finally:
            fcntl.flock(fh, fcntl.LOCK_UN)


def checked_wheels(platform, python, lock):
    """Paths of the locked wheels for (platform, python), downloaded when missing, each checked
    against its SHA-256; PackageError on any mismatch."""
    wanted = lock.get((platform, python))
    if not wanted:
        raise PackageError(f"release/wheels.lock has no wheels for {platform}, Python {python}")
    folder = os.path.join(CACHE, f"{platform}-{python}")
    with _only_one(folder):
        if not all(os.path.isfile(os.path.join(folder, name)) for name, _ in wanted):
            download(platform, python)
    paths = []
    for name, digest in wanted:
        path = os.path.join(folder, name)
        if not os.path.isfile(path):
            raise PackageError(f"{name} was not downloaded (is the pin in the lock file right?)")
        if sha256(path) != digest:
            raise PackageError(f"{name}: SHA-256 {sha256(path)} is not the locked {digest}; "
                               "nothing was packed")
        paths.append(path)
    return paths


def write_lock(path=LOCK):
    """Download every pinned wheel and record its SHA-256 (run when a pin changes)."""
    lines = [f"# {' '.join(PINS)} from PyPI: Blender platform, Python, wheel, SHA-256.",
             "# Written by `./dev package --lock`; `./dev package` packs nothing that differs."]
    for platform, (_, pythons) in PLATFORMS.items():
        for python in pythons:
            for wheel in download(platform, python):
                lines.append(f"{platform} {python} {os.path.basename(wheel)} {sha256(wheel)}")
    with open(path, "w") as fh:
        fh.write("\n".join(lines) + "\n")
    return path


def _manifest_with(text, wheels, platforms, blender_min=None, blender_max=None):
    """The committed manifest's text with `wheels` (when there are any) and `platforms` added
    (top-level keys, before the first table), and its Blender versions narrowed where given
    (`blender_min` replaces blender_version_min; `blender_max`, exclusive, is added)."""
    lines = ["wheels = [", *[f'  "./wheels/{os.path.basename(w)}",' for w in wheels], "]"] if wheels else []
    lines += ["platforms = [" + ", ".join(f'"{p}"' for p in platforms) + "]"]
    if blender_max:
        lines.append(f'blender_version_max = "{blender_max}"')
    head, sep, rest = text.partition("\n[")
    if blender_min:
        head, n = re.subn(r'(?m)^blender_version_min = "[^"]*"$', f'blender_version_min = "{blender_min}"', head)
        if n != 1:
            raise PackageError("the manifest has no blender_version_min line to narrow")
    return head.rstrip("\n") + "\n\n" + "\n".join(lines + [""]) + sep + rest


def stage(wheels, platforms, folder, root=ROOT, **versions):
    """A source folder for Blender's builder: the extension's files in `root` as its manifest
    packs them, the wheels under ./wheels/, and a manifest that lists both (`versions`: Blender
    versions to narrow it to, as `_manifest_with` takes them)."""
    if os.path.isdir(folder):
        shutil.rmtree(folder)
    for rel in eh.planned_files(root):
        os.makedirs(os.path.join(folder, os.path.dirname(rel)), exist_ok=True)
        shutil.copy2(os.path.join(root, rel), os.path.join(folder, rel))
    os.makedirs(os.path.join(folder, "wheels"), exist_ok=True)
    for w in wheels:
        shutil.copy2(w, os.path.join(folder, "wheels", os.path.basename(w)))
    with open(os.path.join(root, "blender_manifest.toml")) as fh:
        text = _manifest_with(fh.read(), wheels, platforms, **versions)
    tomllib.loads(text)                                   # still TOML
    with open(os.path.join(folder, "blender_manifest.toml"), "w") as fh:
        fh.write(text)
    return folder


def locked_wheels(platforms, pythons, lock):
    """The checked wheels for `platforms`, limited to `pythons` (None: every version numba has)."""
    wheels = []
    for platform in platforms:
        chosen = [p for p in PLATFORMS[platform][1] if pythons is None or p in pythons]
        if not chosen:
            raise PackageError(f"numba has no {platform} wheels for Python {', '.join(pythons)}")
        for python in chosen:
            wheels += checked_wheels(platform, python, lock)
    return wheels


def _archive_manifest(path):
    """The manifest inside a package, or None when `path` is no package."""
    try:
        with zipfile.ZipFile(path) as zf:
            return tomllib.loads(zf.read("blender_manifest.toml").decode("utf-8"))
    except (zipfile.BadZipFile, KeyError, UnicodeDecodeError, tomllib.TOMLDecodeError):
        return None


def remove_stale(folder, manifest, any_platform=False):
    """Delete the packages of this extension in `folder` whose version is not `manifest`'s (the
    index must list one version only) and, unless `any_platform`, those for any platform (an
    earlier layout kept one beside the platform packages); other extensions' packages stay.
    Returns what went."""
    gone = []
    if not os.path.isdir(folder):
        return gone
    for name in sorted(os.listdir(folder)):
        path = os.path.join(folder, name)
        if not name.endswith(".zip") or not os.path.isfile(path):
            continue
        other = _archive_manifest(path)
        if not other or other.get("id") != manifest["id"]:
            continue
        if other.get("version") != manifest["version"] or not (any_platform or other.get("platforms")):
            os.remove(path)
            gone.append(path)
    return gone


@contextlib.contextmanager
def source_folder():
    """A new folder under the build folder for one build's staged source, removed on leaving
    (the build done or failed, the staging too): builds may run side by side (the test passes of
    `./dev test` do, in two lanes)."""
    os.makedirs(BUILD, exist_ok=True)
    folder = tempfile.mkdtemp(prefix="source-", dir=BUILD)
    try:
        yield folder
    finally:
        shutil.rmtree(folder, ignore_errors=True)


def build_split(wheels, platforms, out, root=ROOT, blender_min=None):
    """One package per platform from `root` with `wheels` (none: NumPy only), for Blender from
    `blender_min` on (None: the manifest's), by Blender's builder with --split-platforms; their
    paths."""
    with source_folder() as folder:
        stage(wheels, platforms, folder, root, blender_min=blender_min)
        rc, messages = eh.run_extension_cli(
            "build", "--source-dir", folder, "--output-dir", out, "--split-platforms",
            "--valid-tags", eh.blender_tags_file(), timeout=1800)
    if eh._failed(rc, messages):
        raise PackageError("Blender's builder refused the package:\n"
                           + "\n".join(f"{k}: {m}" for k, m in messages))
    manifest = eh.read_manifest(root)
    made = []
    for platform in platforms:
        path = os.path.join(out, f"{manifest['id']}-{manifest['version']}-{platform.replace('-', '_')}.zip")
        if not os.path.isfile(path):
            raise PackageError(f"the builder made no {os.path.basename(path)}: {messages}")
        made.append(path)
    return made


def build_numpy_before(platform, version, out, root=ROOT):
    """A NumPy-only package of `root` for `platform` and the Blender versions before `version`,
    where that platform's numba package starts; its path."""
    manifest = eh.read_manifest(root)
    path = os.path.join(out, f"{manifest['id']}-{manifest['version']}-{platform.replace('-', '_')}"
                             f"-before-{version}.zip")
    with source_folder() as folder:
        stage([], [platform], folder, root, blender_max=version)
        rc, messages = eh.run_extension_cli(
            "build", "--source-dir", folder, "--output-filepath", path,
            "--valid-tags", eh.blender_tags_file(), timeout=600)
    if eh._failed(rc, messages) or not os.path.isfile(path):
        raise PackageError("Blender's builder refused the package:\n"
                           + "\n".join(f"{k}: {m}" for k, m in messages))
    return path


def without_python_311(platforms):
    """Those of `platforms` (with numba wheels) that numba has no Python 3.11 wheels for."""
    return [p for p in platforms if "3.11" not in PLATFORMS[p][1]]


def write_index(folder):
    """index.json and index.html over the packages in `folder`, by Blender's own
    `extension server-generate`; a warning (such as two packages matching one system) is an
    error here, since Blender would then install whichever it reads first. Returns index.json."""
    rc, messages = eh.run_extension_cli("server-generate", "--repo-dir", folder, "--html")
    if eh._failed(rc, messages) or any(kind == "WARN" for kind, _ in messages):
        raise PackageError("Blender's server-generate refused the repository:\n"
                           + "\n".join(f"{k}: {m}" for k, m in messages))
    return os.path.join(folder, "index.json")


def build(platforms, pythons=None, out=DIST, universal=True, numpy_only=NUMPY_ONLY, root=ROOT):
    """Build the packages from `root` into `out`, each validated by Blender, and the repository's
    index over `out`; returns the packages' paths. `platforms`: Blender platform names that get
    numba's wheels; `pythons`: limit the wheels to these Python versions (None: every version
    numba has); `numpy_only`: platforms that get a package without wheels; `universal`: also the
    any-platform package, in out/universal/. A platform without numba's Python 3.11 wheels gets
    its numba package for Blender from PYTHON_313_FROM on, and a NumPy-only one before."""
    clash = set(platforms) & set(numpy_only)
    if clash:
        raise PackageError(f"{sorted(clash)} would get two packages")
    late = without_python_311(platforms)
    early = [p for p in platforms if p not in late]
    lock = read_lock()
    wheels = {tuple(group): locked_wheels(group, pythons, lock)     # before anything is written
              for group in (early, late)}
    manifest = eh.read_manifest(root)
    os.makedirs(out, exist_ok=True)
    made = []
    if universal:
        remove_stale(os.path.join(out, UNIVERSAL), manifest, any_platform=True)
        made.append(eh.build_extension_zip(root, os.path.join(out, UNIVERSAL)))
    remove_stale(out, manifest)
    if early:
        made += build_split(wheels[tuple(early)], early, out, root)
    if late:
        made += build_split(wheels[tuple(late)], late, out, root, blender_min=PYTHON_313_FROM)
    if numpy_only:
        made += build_split([], numpy_only, out, root)
    made += [build_numpy_before(p, PYTHON_313_FROM, out, root) for p in late]
    for path in made:
        eh.validate_manifest(path)
    write_index(out)
    return made


def main(argv=None):
    ap = argparse.ArgumentParser(prog="./dev package", description=__doc__.split("\n\n")[0])
    ap.add_argument("--platform", action="append", choices=sorted(PLATFORMS),
                    help="only this platform (repeatable; default: all)")
    ap.add_argument("--python", action="append", help="only wheels for this Python (e.g. 3.13)")
    ap.add_argument("--out", default=DIST, help="output folder (default: dist/)")
    ap.add_argument("--lock", action="store_true", help="download every wheel, rewrite wheels.lock")
    args = ap.parse_args(argv)
    try:
        if args.lock:
            print(f"package: wrote {os.path.relpath(write_lock(), ROOT)}")
            return 0
        for path in build(args.platform or list(PLATFORMS), args.python, args.out):
            print(f"package: {os.path.relpath(path, ROOT)}  {os.path.getsize(path) / 2 ** 20:.1f} MiB")
        print(f"package: {os.path.relpath(os.path.join(args.out, 'index.json'), ROOT)} and index.html: "
              "the repository's index (serve the folder, or add file:///.../index.json)")
    except (PackageError, eh.ExtensionBuildError, eh.ExtensionValidationError) as exc:
        print(f"package: {exc}", file=sys.stderr)
        return 1
    return 0


if __name__ == "__main__":
    sys.exit(main())
