"""Peak memory of ``skycap process`` on a flight and the continuity of its motion at the fit windows' seams.

    python bench/bench_process_long.py FLIGHT_DIR [FLIGHT_DIR ...] [--analyse-only] [--json OUT] [-- PROCESS ARGS]

    python bench/bench_process_long.py flights/long600 flights/short35 -- --set 'export.extra=[]' --set export.rrd=false

For each flight: ``python -m apps.cli process FLIGHT_DIR [PROCESS ARGS]`` (the default pipeline: the real keypoint
models; ``--keypoints sim``, ``--no-cache`` and ``--set ...`` go after ``--``) in a child process whose resident
memory is sampled every ``--sample-s`` (psutil): ``peak_rss_mb`` is the largest sum over the process and all its
descendants (worker processes included), ``peak_rss_main_mb`` that of the process alone; every ~5 s a line ``seconds tree_mb main_mb peak_tree_mb`` goes
to ``FLIGHT_DIR/bench_process_long.<time>.rss`` (the processing's log beside it). A flight processed earlier
resumes from its ``processing/`` cache (what is then measured is the rest); ``--no-cache`` after ``--`` runs all.

Then, from the motion it wrote (``summary.json`` of its method's folder: the output files and the fit windows):
the largest frame-to-frame joint displacement (``step``, m) and velocity change (``dv``, m/s) at the window seams
(each overlap of two windows, +-``--pad-s``) and inside the windows (:func:`reconstruction.process.windows.seam_figures`),
the same for the simulator's truth (``truth.mcap``, interpolated to the motion's times) when the flight has one,
and how far two neighbouring windows' own fits differ over their overlap (what the cross-fade smooths away; from
the fit cache in ``processing/fit/``). A jump at a seam shows as a seam maximum far above the inside one (and
above the truth's).

``--analyse-only``: do not run the processing, analyse the outputs already in the flight folder.
"""

from __future__ import annotations

import argparse
import json
import subprocess
import sys
import threading
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from bench._machine import describe_machine  # noqa: E402


class TreeRss:
    """Samples the resident memory of a process and all its descendants in a thread."""

    def __init__(self, pid: int, every_s: float = 0.2, log_path: Path | None = None):
        import psutil

        self._psutil = psutil
        self.proc = psutil.Process(pid)
        self.every_s = every_s
        self.peak_tree = 0
        self.peak_main = 0
        self.peak_children = 0
        self.samples = 0
        self.log_path = log_path
        self._t0 = time.perf_counter()
        self._stop = threading.Event()
        self._t = threading.Thread(target=self._run, daemon=True)
        self._t.start()

    def _rss(self, p) -> int:
        try:
            return p.memory_info().rss
        except (self._psutil.NoSuchProcess, self._psutil.AccessDenied):
            return 0

    def _run(self) -> None:
        while not self._stop.is_set():
            try:
                kids = self.proc.children(recursive=True)
            except self._psutil.NoSuchProcess:
                return
            main = self._rss(self.proc)
            total = main + sum(self._rss(k) for k in kids)
            self.peak_main = max(self.peak_main, main)
            self.peak_tree = max(self.peak_tree, total)
            self.peak_children = max(self.peak_children, len(kids))
            self.samples += 1
            if self.log_path is not None and self.samples % max(1, int(round(5.0 / self.every_s))) == 1:
                with open(self.log_path, "a") as f:  # every ~5 s: the memory over time (a run cut short still tells)
                    f.write(f"{time.perf_counter() - self._t0:.1f} {total / 2**20:.1f} {main / 2**20:.1f} "
                            f"{self.peak_tree / 2**20:.1f}\n")
            self._stop.wait(self.every_s)

    def stop(self) -> None:
        self._stop.set()
        self._t.join()


def run_process(flight: Path, extra: list[str], sample_s: float, log_path: Path) -> dict:
    cmd = [sys.executable, "-m", "apps.cli", "process", str(flight), *extra]
    t0 = time.perf_counter()
    with open(log_path, "w") as logf:
        p = subprocess.Popen(cmd, stdout=logf, stderr=subprocess.STDOUT, cwd=Path(__file__).resolve().parents[1])
        mon = TreeRss(p.pid, sample_s, log_path.with_suffix(".rss"))
        rc = p.wait()
        mon.stop()
    wall = time.perf_counter() - t0
    if rc != 0:
        raise SystemExit(f"skycap process {flight} failed (exit {rc}); see {log_path}")
    return {"command": " ".join(cmd[1:]), "wall_s": round(wall, 1), "peak_rss_mb": round(mon.peak_tree / 2**20, 1),
            "peak_rss_main_mb": round(mon.peak_main / 2**20, 1), "max_descendants": mon.peak_children,
            "rss_samples": mon.samples, "log": str(log_path)}


def find_summary(flight: Path) -> Path:
    cands = [p for p in (flight / "reconstruction" / "summary.json", flight / "reconstruction_monocular" / "summary.json")
             if p.is_file()]
    if not cands:
        raise SystemExit(f"{flight}: no reconstruction/summary.json (process the flight first, or leave out --analyse-only)")
    return max(cands, key=lambda p: p.stat().st_mtime)


def truth_joints(flight: Path, t_ns: np.ndarray) -> np.ndarray | None:
    """The simulator's true COCO-17 joints (NED m) interpolated to ``t_ns``; None without a truth."""
    from evaluation.flight import joints_at, read_true_joints

    path = flight / "truth.mcap"
    true = read_true_joints(path) if path.is_file() else None
    return None if true is None else joints_at(*true, t_ns)


def window_disagreement(flight: Path, n_windows: int) -> dict | None:
    """Largest / median joint distance between neighbouring windows' own fits over their shared times (the fit
    cache's newest complete set of ``n_windows`` windows)."""
    fit_dir = flight / "processing" / "fit"
    if n_windows < 2 or not fit_dir.is_dir():
        return None
    groups: dict[str, list[Path]] = {}
    for p in fit_dir.glob("*-w[0-9][0-9][0-9].npz"):
        groups.setdefault(p.name.rsplit("-w", 1)[0], []).append(p)
    full = [sorted(v) for v in groups.values() if len(v) == n_windows]
    if not full:
        return None
    files = max(full, key=lambda v: max(p.stat().st_mtime for p in v))
    res = []
    for p in files:
        with np.load(p) as z:
            res.append((z["t_ns"].astype(np.int64), z["joints_ned"]) if int(z["ok"]) else None)
    worst, meds = 0.0, []
    for a, b in zip(res, res[1:]):
        if a is None or b is None:
            continue
        _, ia, ib = np.intersect1d(a[0], b[0], return_indices=True)
        if not len(ia):
            continue
        d = np.linalg.norm(a[1][ia] - b[1][ib], axis=-1)  # (n, 17)
        worst = max(worst, float(d.max()))
        meds.append(float(np.median(d)))
    return {"max_m": round(worst, 4), "median_m": round(float(np.median(meds)), 4) if meds else None}


def analyse(flight: Path, pad_s: float) -> dict:
    from reconstruction.process.windows import seam_figures

    summary_path = find_summary(flight)
    s = json.loads(summary_path.read_text())
    npz = Path(s["outputs"]["npz"])
    with np.load(npz) as z:
        t_ns = z["t_ns"].astype(np.int64)
        J = np.asarray(z["joints_ned"], dtype=float)
    t00 = int(t_ns[0])
    # summary windows are seconds from the fit grid's start: the motion's first time (the stitched grid)
    windows = [(t00 + int(round(a * 1e9)), t00 + int(round(b * 1e9))) for a, b in s["windows"]]
    out = {"flight": str(flight), "method": s.get("method"), "keypoints_source": s.get("keypoints_source"),
           "frames": int(len(t_ns)), "motion_span_s": s.get("motion_span_s"), "windows": len(windows),
           "processing_s": s.get("seconds"), "steps": s.get("steps"),
           "motion": seam_figures(t_ns, J, windows, pad_s)}
    T = truth_joints(flight, t_ns)
    if T is not None:
        out["truth"] = seam_figures(t_ns, T, windows, pad_s)
    out["window_disagreement"] = window_disagreement(flight, len(windows))
    return out


def fmt(x, nd=3):
    return "-" if x is None else f"{x:.{nd}f}"


def main(argv: list[str] | None = None) -> int:
    argv = list(sys.argv[1:] if argv is None else argv)
    extra: list[str] = []
    if "--" in argv:
        i = argv.index("--")
        argv, extra = argv[:i], argv[i + 1:]
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("flights", nargs="+", type=Path)
    ap.add_argument("--analyse-only", action="store_true", help="do not process, analyse the outputs there")
    ap.add_argument("--sample-s", type=float, default=0.2, help="memory sampling period (s)")
    ap.add_argument("--pad-s", type=float, default=0.5, help="seam zone beyond each window overlap (s)")
    ap.add_argument("--json", type=Path, default=None, help="write the figures here too")
    args = ap.parse_args(argv)
    print(describe_machine())
    rows = []
    for flight in args.flights:
        flight = flight.resolve()
        row: dict = {}
        if not args.analyse_only:
            row["run"] = run_process(flight, extra, args.sample_s, flight / f"bench_process_long.{int(time.time())}.log")
            row["run"]["load_avg_after"] = round(__import__("os").getloadavg()[0], 2)
        row.update(analyse(flight, args.pad_s))
        rows.append(row)
        print(json.dumps(row, indent=1, default=str), flush=True)
    print()
    print(f"{'flight':28s} {'span s':>7s} {'win':>4s} {'peak RSS MB':>11s} {'main MB':>8s} {'proc s':>7s} | "
          f"{'step m seam/inside/truth-max':>30s} | {'dv m/s seam/inside/truth-max':>30s} | {'win diff max/med m':>18s}")
    for r in rows:
        run = r.get("run", {})
        m, tr = r["motion"], r.get("truth") or {}
        tmax_step = max([v for v in (tr.get("step_m_seam_max"), tr.get("step_m_inside_max")) if v is not None], default=None)
        tmax_dv = max([v for v in (tr.get("dv_mps_seam_max"), tr.get("dv_mps_inside_max")) if v is not None], default=None)
        wd = r.get("window_disagreement") or {}
        print(f"{Path(r['flight']).name[:28]:28s} {fmt(r['motion_span_s'], 1):>7s} {r['windows']:>4d} "
              f"{fmt(run.get('peak_rss_mb'), 0):>11s} {fmt(run.get('peak_rss_main_mb'), 0):>8s} "
              f"{fmt(r.get('processing_s'), 0):>7s} | "
              f"{fmt(m['step_m_seam_max']):>9s} {fmt(m['step_m_inside_max']):>9s} {fmt(tmax_step):>9s}  | "
              f"{fmt(m['dv_mps_seam_max'], 2):>9s} {fmt(m['dv_mps_inside_max'], 2):>9s} {fmt(tmax_dv, 2):>9s}  | "
              f"{fmt(wd.get('max_m')):>8s} {fmt(wd.get('median_m')):>8s}")
    if args.json:
        args.json.write_text(json.dumps(rows, indent=1, default=str))
    return 0


if __name__ == "__main__":
    sys.exit(main())
