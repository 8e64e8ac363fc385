"""The 3D-BBS baseline (Aoki et al., ICRA 2024, CPU implementation) for the global-init benchmark.

blockloc never depends on 3D-BBS. The benchmark builds the public C++ library (Eigen, Boost
headers, OpenMP, CMake) together with our line-protocol driver (``bench/baselines/bbs3d/driver.cpp``)
in its own cache directory, and runs it as a child process:

- the source: ``BLOCKLOC_BBS3D_SRC`` (a checkout, or a bare git directory to export the pinned
  commit from), else a clone of :data:`REPO_URL` at :data:`COMMIT` into the cache (needs the network);
- the build: ``~/.cache/blockloc/bbs3d/build-<commit>/bbs3d_driver``.

When it cannot be built, :func:`ensure_built` raises :class:`Unavailable` with the reason in one
line (the benchmark prints it and goes on without the row).

    drv = BBS3D(map_points_map)                  # (N, 3) float, map frame
    res = drv.localize(scan_gravity_aligned, lo, hi)   # T_map_scan (4, 4) and the library's claims
"""

from __future__ import annotations

import json
import os
import shutil
import subprocess
import tempfile
from dataclasses import dataclass
from pathlib import Path

import numpy as np

REPO_URL = "https://github.com/KOKIAOKI/3d_bbs"
COMMIT = "41529a34a2fb9618b5ff560fb3c2363f1615666d"
DRIVER_DIR = Path(__file__).resolve().parent / "baselines" / "bbs3d"


class Unavailable(RuntimeError):
    """3D-BBS cannot be built or run here; the message says why in one line."""


def _cache() -> Path:
    return Path(os.environ.get("BLOCKLOC_CACHE", Path.home() / ".cache" / "blockloc")) / "bbs3d"


def _run(cmd: list[str], cwd: Path | None = None) -> None:
    p = subprocess.run(cmd, cwd=cwd, capture_output=True, text=True)
    if p.returncode != 0:
        tail = (p.stderr or p.stdout).strip().splitlines()[-1:] or ["(no output)"]
        raise Unavailable(f"`{' '.join(cmd[:3])} ...` failed: {tail[0][:200]}")


def _source() -> Path:
    """A directory holding 3D-BBS's ``bbs3d/`` sources at :data:`COMMIT` (or the user's checkout)."""
    given = os.environ.get("BLOCKLOC_BBS3D_SRC")
    out = _cache() / f"src-{COMMIT[:12]}"
    if given:
        g = Path(given)
        if (g / "bbs3d" / "src" / "cpu_bbs3d").is_dir():
            return g  # a work tree: used as it is
        if (g / "objects").is_dir() or (g / "HEAD").is_file():  # a bare git directory
            if not (out / "bbs3d").is_dir():
                tmp = Path(tempfile.mkdtemp(dir=_cache()))
                archive = subprocess.run(["git", "--git-dir", str(g), "archive", COMMIT, "bbs3d"],
                                         capture_output=True)
                if archive.returncode != 0:
                    raise Unavailable(f"BLOCKLOC_BBS3D_SRC={g}: commit {COMMIT[:12]} not found in it")
                subprocess.run(["tar", "-x", "-C", str(tmp)], input=archive.stdout, check=True)
                tmp.rename(out)
            return out
        raise Unavailable(f"BLOCKLOC_BBS3D_SRC={g}: expected a 3d_bbs checkout (with bbs3d/src/cpu_bbs3d)")
    if (out / "bbs3d").is_dir():
        return out
    if shutil.which("git") is None:
        raise Unavailable("git is not installed (needed to fetch 3D-BBS)")
    tmp = Path(tempfile.mkdtemp(dir=_cache()))
    _run(["git", "clone", "--quiet", REPO_URL, str(tmp / "src")])
    _run(["git", "checkout", "--quiet", COMMIT], cwd=tmp / "src")
    (tmp / "src").rename(out)
    return out


def ensure_built() -> Path:
    """The driver executable, built on first use; raises :class:`Unavailable` (one line) if it cannot be."""
    import hashlib

    # One build per driver source and checkout: CMake's cache remembers its source directory, so two
    # checkouts of blockloc must not share a build directory.
    key = hashlib.sha1(str(DRIVER_DIR).encode() + b"".join(
        (DRIVER_DIR / f).read_bytes() for f in ("driver.cpp", "CMakeLists.txt"))).hexdigest()[:10]
    build = _cache() / f"build-{COMMIT[:12]}-{key}"
    exe = build / "bbs3d_driver"
    if exe.is_file():
        return exe
    for tool in ("cmake", "make", "c++"):
        if shutil.which(tool) is None:
            raise Unavailable(f"{tool} is not installed (3D-BBS is C++; build-essential and cmake are needed)")
    if not Path("/usr/include/eigen3").is_dir():
        raise Unavailable("Eigen3 headers missing (apt install libeigen3-dev)")
    if not Path("/usr/include/boost/functional/hash.hpp").is_file():
        raise Unavailable("Boost headers missing (apt install libboost-dev)")
    _cache().mkdir(parents=True, exist_ok=True)
    src = _source()
    build.mkdir(parents=True, exist_ok=True)
    _run(["cmake", "-S", str(DRIVER_DIR), "-B", str(build), f"-DBBS3D_SRC={src}", "-DCMAKE_BUILD_TYPE=Release"])
    _run(["cmake", "--build", str(build), "-j", "2"])
    if not exe.is_file():
        raise Unavailable(f"the build finished without {exe}")
    return exe


@dataclass
class BBSResult:
    T_map_scan: np.ndarray  # (4, 4)
    localized: bool  # the library's claim: score above its threshold
    timed_out: bool
    score_pct: float  # share of scan voxels that hit the map at the best pose
    search_s: float  # the library's own timing of localize()


class BBS3D:
    """One driver process holding one map's voxel pyramid.

    Args:
        map_points: (N, 3) map points in the map frame (m), downsampled by the caller.
        min_level_res: finest voxel (m); the published outdoor setting is 1.0.
        max_level: pyramid levels above it (published: 6).
        threads: OpenMP threads (the machine's cores).
    """

    def __init__(self, map_points: np.ndarray, min_level_res: float = 1.0, max_level: int = 6, threads: int = 2):
        self._dir = Path(tempfile.mkdtemp(prefix="blockloc-bbs3d-"))
        self._proc = subprocess.Popen([str(ensure_built())], stdin=subprocess.PIPE, stdout=subprocess.PIPE,
                                      text=True, bufsize=1)
        path = self._dir / "map.bin"
        np.ascontiguousarray(map_points, dtype="<f8").tofile(path)
        ans = self._ask(f"map {path} {min_level_res} {max_level} {threads}")
        self.prep_s = ans["prep_ms"] / 1e3

    def _ask(self, line: str) -> dict:
        assert self._proc.stdin is not None and self._proc.stdout is not None
        self._proc.stdin.write(line + "\n")
        self._proc.stdin.flush()
        out = self._proc.stdout.readline()
        if not out:
            raise Unavailable(f"the 3D-BBS driver exited (code {self._proc.poll()})")
        ans = json.loads(out)
        if "error" in ans:
            raise Unavailable(f"the 3D-BBS driver: {ans['error']}")
        return ans

    def localize(self, scan: np.ndarray, lo_xyz, hi_xyz, rpy_lo=(-0.02, -0.02, 0.0),
                 rpy_hi=(0.02, 0.02, 2 * np.pi), score_pct: float = 0.9, timeout_s: float = 0.0) -> BBSResult:
        """Searches for T_map_scan.

        Args:
            scan: (M, 3) gravity-aligned scan points (m), downsampled by the caller.
            lo_xyz, hi_xyz: the translation search box (map frame, m).
            rpy_lo, rpy_hi: the angle ranges (rad); the library's defaults search all yaw.
            score_pct: the share of scan points that must hit for ``localized`` (published: 0.9).
            timeout_s: 0 = none.
        """
        path = self._dir / "scan.bin"
        np.ascontiguousarray(scan, dtype="<f8").tofile(path)
        nums = [*lo_xyz, *hi_xyz, *rpy_lo, *rpy_hi]
        ans = self._ask(f"loc {path} " + " ".join(f"{float(v):.9g}" for v in nums)
                        + f" {score_pct} {int(round(timeout_s * 1e3))}")
        return BBSResult(np.asarray(ans["T"], float).reshape(4, 4), bool(ans["localized"]), bool(ans["timed_out"]),
                         float(ans["score_pct"]), float(ans["ms"]) / 1e3)

    def cpu_s(self) -> float:
        """CPU seconds (user + system, all threads) the driver process has used so far (Linux /proc)."""
        try:
            fields = Path(f"/proc/{self._proc.pid}/stat").read_text().rsplit(")", 1)[1].split()
        except OSError:
            return float("nan")
        return (int(fields[11]) + int(fields[12])) / os.sysconf("SC_CLK_TCK")

    def close(self) -> None:
        if self._proc.poll() is None:
            try:
                self._ask("quit")
            except (Unavailable, ValueError, BrokenPipeError):
                pass
            self._proc.wait(timeout=10)
        shutil.rmtree(self._dir, ignore_errors=True)

    def __enter__(self) -> "BBS3D":
        return self

    def __exit__(self, *exc) -> None:
        self.close()


def localize_hinted(drv: BBS3D, points_body: np.ndarray, gravity_body: np.ndarray, R_L_map: np.ndarray,
                    center_L: np.ndarray, window_m: float, z_range_L: tuple[float, float],
                    scan_voxel_m: float = 2.0, max_range_m: float = 100.0,
                    timeout_s: float = 0.0) -> tuple[np.ndarray, BBSResult]:
    """3D-BBS on one scan with a hint: T_map_body (4, 4) and the library's result.

    The scan is levelled with the same gravity our search gets (3D-BBS expects gravity-aligned
    scans), cropped to ``max_range_m`` and thinned to one point per ``scan_voxel_m`` voxel (its
    published outdoor settings: 2 m, 100 m). The translation box is the hint's window
    (``window_m`` square about ``center_L``, level frame) over the map's height range ``z_range_L``;
    yaw is unknown (full turn), roll and pitch +-0.02 rad as published.

    Args:
        points_body: (M, 3) scan, body frame (m).
        gravity_body: (3,) gravity in the body frame.
        R_L_map: (3, 3) the map's level frame; the driver's map must be in that frame.
        center_L: (2,) window centre, level frame (m).
    """
    from blockloc.global_init.projection import R_level_from_gravity
    from blockloc.voxels import voxel_select

    R_lvl_body = R_level_from_gravity(gravity_body)
    pts = np.asarray(points_body, float)
    pts = pts[np.linalg.norm(pts, axis=1) <= max_range_m] @ R_lvl_body.T
    pts = pts[voxel_select(pts, scan_voxel_m)]
    h = 0.5 * window_m
    lo = (center_L[0] - h, center_L[1] - h, z_range_L[0])
    hi = (center_L[0] + h, center_L[1] + h, z_range_L[1])
    res = drv.localize(pts, lo, hi, timeout_s=timeout_s)
    T_map_L = np.eye(4)
    T_map_L[:3, :3] = R_L_map.T
    T_lvl_body = np.eye(4)
    T_lvl_body[:3, :3] = R_lvl_body
    return T_map_L @ res.T_map_scan @ T_lvl_body, res
