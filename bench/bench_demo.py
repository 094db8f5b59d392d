"""Benchmark of a demo run: per-process CPU use and the rates achieved (from the flight's summary.json).

    python bench/bench_demo.py                       # 3 drones, 60 s of orbit, into /tmp/skycap_bench_demo
    python bench/bench_demo.py --drones 2 --duration 30 -- --set cameras=false

Runs ``skycap demo`` as a child process and samples every descendant's CPU time from /proc once a second
(Linux). CPU % is of one core (100 % = one core busy), averaged over each process's life; "peak" is the
highest 5-s average. Prints the machine, a per-process table and the summary table.
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent))
from _machine import describe_machine  # noqa: E402

CLK = os.sysconf("SC_CLK_TCK")


def _children(pid: int) -> list[int]:
    out = []
    try:
        for task in os.listdir(f"/proc/{pid}/task"):
            with open(f"/proc/{pid}/task/{task}/children") as f:
                out += [int(x) for x in f.read().split()]
    except OSError:
        pass
    return out


def _descendants(pid: int) -> list[int]:
    seen, todo = [], [pid]
    while todo:
        p = todo.pop()
        seen.append(p)
        todo += _children(p)
    return seen


def _cpu_s(pid: int) -> float | None:
    try:
        with open(f"/proc/{pid}/stat") as f:
            parts = f.read().rsplit(")", 1)[1].split()
        return (int(parts[11]) + int(parts[12])) / CLK  # utime + stime
    except (OSError, IndexError, ValueError):
        return None


def _name(pid: int) -> str:
    try:
        with open(f"/proc/{pid}/cmdline", "rb") as f:
            argv = f.read().decode(errors="replace").split("\0")
    except OSError:
        return str(pid)
    if "agent" in argv and "--drone-id" in argv:
        return "agent " + argv[argv.index("--drone-id") + 1]
    if "sim" in argv and "--fleet" in argv:
        return "simulator node"
    if "--drone-id" in argv:
        return "camera " + argv[argv.index("--drone-id") + 1]
    if "demo" in argv:
        return "launcher + fleet client"
    if "reconstruct" in argv:
        return "reconstruct"
    return " ".join(Path(a).name for a in argv[:3])


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--drones", type=int, default=3)
    ap.add_argument("--duration", type=float, default=60.0)
    ap.add_argument("--out", type=Path, default=None, help="a new flight folder (default: a fresh temporary one)")
    ap.add_argument("extra", nargs="*", help="more arguments for skycap demo (after --)")
    args = ap.parse_args()
    if args.out is None:  # the demo never writes into a folder that holds a flight
        import tempfile

        args.out = Path(tempfile.mkdtemp(prefix="skycap_bench_demo_")) / "flight"
    cmd = [sys.executable, "-m", "apps.cli", "demo", "--drones", str(args.drones), "--duration", str(args.duration),
           "--out", str(args.out), *args.extra]
    t0 = time.monotonic()
    proc = subprocess.Popen(cmd, stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True)
    stats: dict[int, dict] = {}
    import threading

    lines: list[str] = []
    reader = threading.Thread(target=lambda: lines.extend(proc.stdout), daemon=True)
    reader.start()
    while proc.poll() is None:
        now = time.monotonic()
        for pid in _descendants(proc.pid):
            c = _cpu_s(pid)
            if c is None:
                continue
            s = stats.setdefault(pid, {"name": _name(pid), "t0": now, "c0": c, "samples": []})
            s["samples"].append((now, c))
            s["t1"], s["c1"] = now, c
        time.sleep(1.0)
    reader.join(5)
    wall = time.monotonic() - t0
    print(f"machine: {describe_machine()} (load average sampled at the end of the run)")
    print(f"skycap demo --drones {args.drones} --duration {args.duration:.0f}: exit {proc.returncode}, wall {wall:.0f} s\n")
    rows = []
    by_name: dict[str, list] = {}
    for s in stats.values():
        by_name.setdefault(s["name"], []).append(s)
    for name, group in by_name.items():
        life = sum(g.get("t1", g["t0"]) - g["t0"] for g in group)
        used = sum(g.get("c1", g["c0"]) - g["c0"] for g in group)
        peak = 0.0
        for g in group:
            smp = g["samples"]
            for i in range(len(smp)):
                j = next((k for k in range(i, len(smp)) if smp[k][0] - smp[i][0] >= 5.0), None)
                if j is not None:
                    peak = max(peak, (smp[j][1] - smp[i][1]) / (smp[j][0] - smp[i][0]))
        rows.append((name, life, used, 100 * used / life if life > 0 else 0.0, 100 * peak))
    print(f"{'process':28s} {'alive_s':>8s} {'cpu_s':>8s} {'cpu_%':>7s} {'peak_%':>7s}")
    for name, life, used, pct, peak in sorted(rows):
        print(f"{name:28s} {life:8.1f} {used:8.1f} {pct:7.1f} {peak:7.1f}")
    total = sum(r[2] for r in rows)
    print(f"{'total':28s} {wall:8.1f} {total:8.1f} {100 * total / wall:7.1f}\n")
    summary = args.out / "summary.json"
    if summary.is_file():
        from evaluation.flight import format_table

        print(format_table(json.loads(summary.read_text())))
    else:
        print("no summary.json; demo output tail:\n" + "".join(lines[-40:]))
    return proc.returncode or 0


if __name__ == "__main__":
    sys.exit(main())
