"""``skycap camera probe``: what a source really delivers: size, frame rate, frame-interval jitter, capture ->
receive latency and drops, over a few seconds.

    report = probe(open_source(cfg, open_now=False), seconds=5.0)
    print(format_report(report))

Intervals are differences of consecutive ``t_capture_ns`` (the capture clock as each source's latency model
gives it); latency is ``t_received_ns - t_capture_ns`` (for sources without their own capture timestamp it is
just the configured ``latency_s`` plus the time to decode).
"""

from __future__ import annotations

import dataclasses
import time

import numpy as np

from onboard.camera.errors import CameraSourceError
from onboard.camera.sources import FrameSource

__all__ = ["ProbeReport", "probe", "format_report"]


@dataclasses.dataclass
class ProbeReport:
    source: str
    latency_model: str
    seconds: float  #: how long it read
    frames: int
    dropped: int
    width_px: int = 0
    height_px: int = 0
    first_frame_s: float = float("nan")  #: from open to the first frame
    fps_mean: float = float("nan")  #: (frames - 1) / (last - first capture time)
    interval_mean_ms: float = float("nan")
    interval_std_ms: float = float("nan")  #: frame-interval jitter (standard deviation)
    interval_p99_ms: float = float("nan")
    jitter_p99_ms: float = float("nan")  #: 99th percentile of |interval - median interval|
    #: the same on the receive times: how evenly frames reach the reader (the capture clock may be ideal)
    arrival_interval_std_ms: float = float("nan")
    arrival_jitter_p99_ms: float = float("nan")
    latency_mean_ms: float = float("nan")  #: capture -> receive
    latency_p99_ms: float = float("nan")
    latency_max_ms: float = float("nan")
    non_monotonic: int = 0  #: capture times that did not increase
    sizes_changed: int = 0

    def to_dict(self) -> dict:
        return {k: (None if isinstance(v, float) and not np.isfinite(v) else v)
                for k, v in dataclasses.asdict(self).items()}


def probe(source: FrameSource, seconds: float = 5.0, *, open_timeout_s: float = 5.0) -> ProbeReport:
    """Open ``source`` (if needed), read it for ``seconds`` after its first frame (or until it ends), close it and
    measure. Raises :class:`CameraSourceError` when no frame came within ``open_timeout_s``."""
    t_open = time.monotonic()
    source.open()
    frames = []
    dropped0 = source.stats.dropped
    try:
        t_first = None
        while True:
            now = time.monotonic()
            if t_first is None and now - t_open > open_timeout_s:
                why = source.stats.last_error or "nothing arrived"
                raise CameraSourceError(f"{source.describe()}: no frame within {open_timeout_s:.1f} s ({why})")
            if t_first is not None and now - t_first >= seconds:
                break
            f = source.read(0.2)
            if f is None:
                if source.ended:
                    if t_first is None:
                        why = source.stats.last_error or "the stream ended"
                        raise CameraSourceError(f"{source.describe()}: no frame ({why})")
                    break
                continue
            if t_first is None:
                t_first = time.monotonic()
                dropped0 = source.stats.dropped
            frames.append((f.t_capture_ns, f.t_received_ns, f.width_px, f.height_px))
    finally:
        source.close()
    elapsed = time.monotonic() - t_first if t_first is not None else 0.0
    r = ProbeReport(source=source.describe(), latency_model=source.latency_model, seconds=elapsed,
                    frames=len(frames), dropped=int(source.stats.dropped - dropped0))
    if not frames:
        return r
    r.first_frame_s = t_first - t_open
    arr = np.array([f[:2] for f in frames], dtype=np.int64)
    r.width_px, r.height_px = frames[-1][2], frames[-1][3]
    r.sizes_changed = sum(1 for a, b in zip(frames, frames[1:]) if a[2:] != b[2:])
    lat_ms = (arr[:, 1] - arr[:, 0]) / 1e6
    r.latency_mean_ms, r.latency_p99_ms = float(lat_ms.mean()), float(np.percentile(lat_ms, 99))
    r.latency_max_ms = float(lat_ms.max())
    if len(frames) >= 2:
        iv_ms = np.diff(arr[:, 0]) / 1e6
        r.non_monotonic = int((iv_ms <= 0).sum())
        span_s = (arr[-1, 0] - arr[0, 0]) / 1e9
        r.fps_mean = (len(frames) - 1) / span_s if span_s > 0 else float("nan")
        r.interval_mean_ms, r.interval_std_ms = float(iv_ms.mean()), float(iv_ms.std())
        r.interval_p99_ms = float(np.percentile(iv_ms, 99))
        r.jitter_p99_ms = float(np.percentile(np.abs(iv_ms - np.median(iv_ms)), 99))
        rv_ms = np.diff(arr[:, 1]) / 1e6
        r.arrival_interval_std_ms = float(rv_ms.std())
        r.arrival_jitter_p99_ms = float(np.percentile(np.abs(rv_ms - np.median(rv_ms)), 99))
    return r


def format_report(r: ProbeReport) -> str:
    """A small two-column table."""

    def ms(v: float) -> str:
        return "-" if not np.isfinite(v) else f"{v:.2f} ms"

    rows = [
        ("source", r.source),
        ("latency model", r.latency_model),
        ("resolution", f"{r.width_px}x{r.height_px}" if r.frames else "-"),
        ("frames", f"{r.frames} in {r.seconds:.2f} s"),
        ("dropped", str(r.dropped)),
        ("mean fps", "-" if not np.isfinite(r.fps_mean) else f"{r.fps_mean:.2f}"),
        ("first frame after", "-" if not np.isfinite(r.first_frame_s) else f"{r.first_frame_s:.2f} s"),
        ("interval mean", ms(r.interval_mean_ms)),
        ("interval jitter std", ms(r.interval_std_ms)),
        ("interval p99", ms(r.interval_p99_ms)),
        ("|jitter| p99", ms(r.jitter_p99_ms)),
        ("arrival jitter std", ms(r.arrival_interval_std_ms)),
        ("arrival |jitter| p99", ms(r.arrival_jitter_p99_ms)),
        ("capture->receive mean", ms(r.latency_mean_ms)),
        ("capture->receive p99", ms(r.latency_p99_ms)),
        ("capture->receive max", ms(r.latency_max_ms)),
    ]
    if r.non_monotonic:
        rows.append(("NON-MONOTONIC capture times", str(r.non_monotonic)))
    width = max(len(k) for k, _ in rows)
    return "\n".join(f"{k:<{width}}  {v}" for k, v in rows)
