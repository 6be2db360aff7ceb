"""Blender's real window on a virtual display: Debian's `blender` (the e2e chroot) under Xvfb.

    results, shots = run_session(out_dir)     # runs gui_session.py in the window

Xvfb, xwd and xdotool (Debian's `xvfb`, `x11-apps`, `xdotool`) are installed with apt-get when
missing. The chroot's
Blender reaches the host's Xvfb through X's abstract socket, so no mounts are needed. Screenshots
are taken on the host with `xwd -root` when the session asks for one (a `shot-NAME.request` file)
and written as PNG (`shot-NAME.png`); Blender's own screenshot operator reads a black front buffer
under Xvfb. A key press asked for with a `key-KEYSYM.request` file is sent with `xdotool key`, a real
X event that reaches Blender's own event queue. Standard library, NumPy and Pillow only.
"""
import json
import os
import shutil
import struct
import subprocess
import time

import numpy as np

from . import blender_chroot as bc

HERE = os.path.dirname(os.path.abspath(__file__))
SESSION = os.path.join(HERE, "gui_session.py")
SCREEN = (1920, 1080)


class DisplayUnavailable(RuntimeError):
    """No virtual display can be started here (no Xvfb and no apt-get to install it)."""


def _ensure_tools():
    missing = [pkg for tool, pkg in (("Xvfb", "xvfb"), ("xwd", "x11-apps"), ("xdotool", "xdotool"))
               if shutil.which(tool) is None]
    if not missing:
        return
    if shutil.which("apt-get") is None or os.geteuid() != 0:
        raise DisplayUnavailable(f"{', '.join(missing)} missing and not installable here")
    cmd = ["apt-get", "install", "-y", "-q", "--no-install-recommends"] + missing
    env = dict(os.environ, DEBIAN_FRONTEND="noninteractive")
    if subprocess.run(cmd, env=env, capture_output=True).returncode != 0:
        subprocess.run(["apt-get", "update", "-q"], env=env, capture_output=True)
        proc = subprocess.run(cmd, env=env, capture_output=True, text=True)
        if proc.returncode != 0:
            raise RuntimeError(f"apt-get install {' '.join(missing)} failed:\n{proc.stderr[-2000:]}")


def _display_taken(n):
    """Whether X display :n is in use: its lock names a running process, or its socket exists
    with no lock to say whose. A lock left by a server that is gone (killed before it could
    clean up) does not count: Xvfb replaces a stale lock itself."""
    lock = f"/tmp/.X{n}-lock"
    try:
        with open(lock) as fh:
            pid = int(fh.read().strip() or 0)
    except FileNotFoundError:
        return os.path.exists(f"/tmp/.X11-unix/X{n}")
    except (OSError, ValueError):
        return True
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    except PermissionError:
        return True
    return True


def stop_display(proc):
    """End Xvfb so that it removes its lock and socket (a killed one leaves them behind)."""
    proc.terminate()
    try:
        proc.wait(timeout=10)
    except subprocess.TimeoutExpired:
        proc.kill()
        proc.wait()


def start_display():
    """(Popen of Xvfb, display string) on the first free display number from 90."""
    _ensure_tools()
    for n in range(90, 120):
        if _display_taken(n):
            continue
        proc = subprocess.Popen(["Xvfb", f":{n}", "-screen", "0", f"{SCREEN[0]}x{SCREEN[1]}x24",
                                 "-nolisten", "tcp"], stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
        for _ in range(100):
            if os.path.exists(f"/tmp/.X11-unix/X{n}"):
                return proc, f":{n}"
            if proc.poll() is not None:
                break
            time.sleep(0.05)
        stop_display(proc)
    raise RuntimeError("could not start Xvfb on displays :90 to :119")


def read_xwd(path):
    """(H, W, 3) uint8 RGB of a 32-bit TrueColor XWD dump (what `xwd -root` writes on Xvfb)."""
    with open(path, "rb") as fh:
        data = fh.read()
    h = struct.unpack(">25I", data[:100])
    header_size, byte_order, bpp, bpl, w, hgt, ncolors = h[0], h[7], h[11], h[12], h[4], h[5], h[19]
    if bpp != 32:
        raise ValueError(f"{path}: {bpp} bits per pixel, expected 32")
    px = np.frombuffer(data, np.uint8, count=bpl * hgt, offset=header_size + 12 * ncolors)
    px = px.reshape(hgt, bpl)[:, :w * 4].reshape(hgt, w, 4)
    return np.ascontiguousarray(px[:, :, [2, 1, 0]] if byte_order == 0 else px[:, :, [1, 2, 3]])


def capture(display, png_path):
    from PIL import Image
    raw = png_path + ".xwd"
    with open(raw, "wb") as fh:
        subprocess.run(["xwd", "-root", "-silent", "-display", display], stdout=fh, check=True)
    Image.fromarray(read_xwd(raw)).save(png_path + ".part.png")
    os.remove(raw)
    os.replace(png_path + ".part.png", png_path)      # the session waits for the final name


def prepare_workdir():
    """A chroot work folder with this working tree's extension installed and enabled, and the
    splash screen off (as after a user's first start)."""
    bc.ensure_chroot()
    work = bc.new_workdir()
    zip_path = bc.build_extension(bc.REPO_ROOT, work)
    bc.install_extension(zip_path, work)
    rc, out, err, _ = bc.run_blender(
        ["-b", "--python-expr", "import bpy; bpy.context.preferences.view.show_splash = False; "
                                "bpy.ops.wm.save_userpref()"], workdir=work)
    if rc != 0:
        raise RuntimeError(f"could not save the preferences:\n{out[-2000:]}\n{err[-2000:]}")
    return work


def run_session(timeout=600, keep=False):
    """Run gui_session.py in Blender's window. Returns (results dict, {shot name: PNG path}, work
    folder host path); the PNGs lie in the work folder (remove it with blender_chroot.remove_workdir)."""
    work = prepare_workdir()
    out = os.path.join(work, "gui_out")
    os.makedirs(out, exist_ok=True)
    bc.copy_files([SESSION], work)
    xvfb, display = start_display()
    root = bc.chroot_dir()
    inside = "/" + os.path.relpath(work, root)
    env = {"PATH": "/usr/sbin:/usr/bin:/sbin:/bin", "HOME": inside + "/home", "LANG": "C.UTF-8",
           "BLENDER_USER_RESOURCES": inside + "/user_resources", "DISPLAY": display}
    cmd = [bc._chroot_cmd(), root, "/bin/sh", "-c", 'cd "$0" && exec blender "$@"', inside,
           "--python", inside + "/gui_session.py", "--", inside + "/gui_out"]
    log_path = os.path.join(work, "gui.log")
    shots = {}
    try:
        with open(log_path, "w") as log:
            proc = subprocess.Popen(cmd, env=env, stdin=subprocess.DEVNULL, stdout=log, stderr=subprocess.STDOUT)
            t0 = time.time()
            while proc.poll() is None and time.time() - t0 < timeout:
                for name in sorted(os.listdir(out)):
                    if name.startswith("key-") and name.endswith(".request"):
                        # Focus follows the pointer without a window manager: point at Blender.
                        key = name[len("key-"):-len(".request")]
                        subprocess.run(["xdotool", "mousemove", str(SCREEN[0] // 2), str(SCREEN[1] // 2),
                                        "key", key], env=dict(os.environ, DISPLAY=display), check=True)
                        os.remove(os.path.join(out, name))
                    elif name.endswith(".request"):
                        shot = name[len("shot-"):-len(".request")]
                        png = os.path.join(out, f"shot-{shot}.png")
                        time.sleep(0.3)              # let the window finish its redraw
                        capture(display, png)
                        os.remove(os.path.join(out, name))
                        shots[shot] = png
                time.sleep(0.1)
            if proc.poll() is None:
                proc.kill()
                proc.wait()
    finally:
        stop_display(xvfb)
    results_path = os.path.join(out, "results.json")
    if not os.path.exists(results_path):
        with open(log_path) as fh:
            tail = fh.read()[-4000:]
        raise RuntimeError(f"the window session wrote no results (exit {proc.returncode}):\n{tail}")
    with open(results_path) as fh:
        results = json.load(fh)
    return results, shots, work
