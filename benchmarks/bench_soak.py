"""A long live run of `sunrig run` with every device failing on a schedule: growth and clean stop.

Does the rig's memory, descriptor or thread count grow, and does it stop cleanly at the end?

What a vehicle rig meets over a day is a camera stream that drops, a GNSS link that goes away and
a controller that stops reading. This runs the real command, as a subprocess, against real
stand-ins for each, on this machine:

- **camera**: an MJPEG stream over HTTP (``opencv:http://127.0.0.1:PORT/stream.mjpg``, read by
  OpenCV's FFmpeg backend as a network camera would be): the bundled drive at 10 Hz, looped. The
  server cuts the connection every ``--camera-drop-s``, and the camera reconnects.
- **heading**: a GNSS compass as a TCP NMEA server (``nmea:socket://127.0.0.1:PORT``): HDT and RMC
  at 10 Hz, the heading of the frame being served, the UTC of now. It cuts the connection every
  ``--gnss-drop-s``, and the reader reconnects.
- **controller**: a pseudo-terminal (``--serial /dev/pts/N``) whose reader stops reading for
  ``--serial-stall-s`` every minute, so the serial writer times out, drops and reopens the port.
- **outputs**: ``--jsonl`` to a file and ``--record`` (estimates) to a new log.

Every 5 s it samples the rig process's resident memory, open descriptors and threads from /proc.
The memory trend is a least-squares slope over the samples after ``--warmup-s``. At the end it
sends SIGTERM, as systemd or docker would, and checks the exit code, that the recording replays and
that the JSONL has one line per estimate. Prints JSON. Linux only (/proc, pseudo-terminals).

    python3 benchmarks/bench_soak.py [--minutes 10] [--model DIR]

The rig's outputs go to a new folder under the system's temporary one, which the JSON names
(``output_folder``) and which is kept to be looked at; a run stopped early (Ctrl-C, SIGTERM)
stops the rig and removes it.
"""

from __future__ import annotations

import argparse
import json
import os
import shutil
import signal
import socket
import subprocess
import sys
import tempfile
import threading
import time
from datetime import UTC, datetime
from http.server import BaseHTTPRequestHandler, ThreadingHTTPServer
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent.parent))

from benchmarks.common import float_in, machine, run  # noqa: E402

FPS = 10.0
SAMPLE_EVERY_S = 5.0


def nmea(body: str) -> bytes:
    from rig.protocol import nmea_checksum

    return f"${body}*{nmea_checksum(body.encode('ascii')):02X}\r\n".encode("ascii")


class DemoStream:
    """The bundled drive as JPEG bytes and headings, and which frame is being served now."""

    def __init__(self) -> None:
        import math

        import cv2

        from replay.sources import DEMO_LOG, open_frames

        frames = list(open_frames(DEMO_LOG))
        self.jpegs = [cv2.imencode(".jpg", f.image_bgr, [cv2.IMWRITE_JPEG_QUALITY, 90])[1].tobytes() for f in frames]
        self.headings_deg = [math.degrees(f.attitude.heading_rad) % 360.0 for f in frames]
        self.t0 = time.monotonic()

    def index(self) -> int:
        return int((time.monotonic() - self.t0) * FPS) % len(self.jpegs)


class Cuts:
    """Counts the connections a stand-in cut on purpose, and serves until its stop event."""

    def __init__(self, every_s: float, stop: threading.Event) -> None:
        self.every_s, self.stop = every_s, stop
        self.connections = self.cuts = 0


def camera_server(drive: DemoStream, cuts: Cuts) -> ThreadingHTTPServer:
    class Stream(BaseHTTPRequestHandler):
        def log_message(self, *args) -> None:  # quiet: the benchmark prints JSON only
            pass

        def do_GET(self) -> None:
            cuts.connections += 1
            self.send_response(200)
            self.send_header("Content-Type", "multipart/x-mixed-replace; boundary=frame")
            self.end_headers()
            end = time.monotonic() + cuts.every_s
            try:
                while not cuts.stop.is_set():
                    if time.monotonic() >= end:
                        cuts.cuts += 1
                        return  # the server closes the connection: a camera stream that dropped
                    jpg = drive.jpegs[drive.index()]
                    self.wfile.write(b"--frame\r\nContent-Type: image/jpeg\r\nContent-Length: %d\r\n\r\n%b\r\n"
                                     % (len(jpg), jpg))
                    time.sleep(1.0 / FPS)
            except (BrokenPipeError, ConnectionResetError):
                pass

    server = ThreadingHTTPServer(("127.0.0.1", 0), Stream)
    server.daemon_threads = True
    threading.Thread(target=server.serve_forever, name="camera-server", daemon=True).start()
    return server


def gnss_server(drive: DemoStream, cuts: Cuts) -> socket.socket:
    listener = socket.create_server(("127.0.0.1", 0))

    def serve() -> None:
        listener.settimeout(0.5)
        while not cuts.stop.is_set():
            try:
                conn, _ = listener.accept()
            except TimeoutError:
                continue
            except OSError:
                if cuts.stop.is_set():
                    return  # the benchmark closed the listener as it ended: no traceback for that
                raise
            cuts.connections += 1
            end = time.monotonic() + cuts.every_s
            with conn:
                try:
                    while not cuts.stop.is_set() and time.monotonic() < end:
                        now = datetime.now(UTC)
                        hhmmss = now.strftime("%H%M%S") + f".{now.microsecond // 10000:02d}"
                        conn.sendall(nmea(f"GPHDT,{drive.headings_deg[drive.index()]:.1f},T")
                                     + nmea(f"GPRMC,{hhmmss},A,4807.038,N,01131.000,E,10.0,0.0,"
                                            f"{now.strftime('%d%m%y')},,,A"))
                        time.sleep(1.0 / FPS)
                    cuts.cuts += not cuts.stop.is_set()
                except (BrokenPipeError, ConnectionResetError):
                    pass

    threading.Thread(target=serve, name="gnss-server", daemon=True).start()
    return listener


def serial_reader(master: int, stall_s: float, stop: threading.Event, counts: dict) -> None:
    """Reads the controller's side of the pty, but stops reading for ``stall_s`` every minute."""
    os.set_blocking(master, False)
    start = time.monotonic()
    while not stop.is_set():
        if (time.monotonic() - start) % 60.0 >= 60.0 - stall_s:
            stop.wait(0.5)
            continue
        try:
            counts["bytes"] += len(os.read(master, 65536))
        except BlockingIOError:
            stop.wait(0.05)
        except OSError:  # EIO while the rig has the port closed between timeout and reopen
            stop.wait(0.05)


def sample(pid: int) -> dict | None:
    try:
        status = Path(f"/proc/{pid}/status").read_text()
        fds = len(os.listdir(f"/proc/{pid}/fd"))
    except (FileNotFoundError, ProcessLookupError):
        return None
    fields = dict(line.split(":", 1) for line in status.splitlines() if ":" in line)
    return {"rss_mb": int(fields["VmRSS"].split()[0]) / 1024.0, "threads": int(fields["Threads"]), "fds": fds}


def stop_rig(proc: subprocess.Popen, wait_s: float) -> int | None:
    """Stop the rig as a service manager would (SIGTERM); one that has not ended within ``wait_s``
    gets SIGABRT (its thread dump, with PYTHONFAULTHANDLER) and then is killed. Its exit code, or
    None if it had to be killed."""
    if proc.poll() is None:
        proc.send_signal(signal.SIGTERM)
    try:
        return proc.wait(timeout=wait_s)
    except subprocess.TimeoutExpired:
        proc.send_signal(signal.SIGABRT)  # the thread dump, then the end
        try:
            proc.wait(timeout=10.0)
        except subprocess.TimeoutExpired:
            proc.kill()
        return None


def slope_per_hour(ts: list[float], ys: list[float]) -> float | None:
    """Least-squares slope of ys over ts (seconds), per hour."""
    import numpy as np

    if len(ts) < 3 or len(set(ts)) < 2:
        return None
    return 3600.0 * float(np.polyfit(ts, ys, 1)[0])


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--minutes", type=float_in(0.0), default=10.0)
    ap.add_argument("--model", help="model folder (default: the shipped model)")
    ap.add_argument("--warmup-s", type=float_in(0.0, lo_included=True), default=60.0,
                    help="left out of the memory trend (default 60)")
    ap.add_argument("--camera-drop-s", type=float_in(0.0), default=90.0)
    ap.add_argument("--gnss-drop-s", type=float_in(0.0), default=60.0)
    ap.add_argument("--serial-stall-s", type=float_in(0.0, 60.0, lo_included=True), default=30.0,
                    help="seconds of each minute the controller does not read (default 30: the pty's "
                         "buffer holds about 20 s of sentences, so the writer times out and reopens)")
    args = ap.parse_args()
    if sys.platform != "linux":
        sys.exit("bench_soak: needs Linux (/proc and pseudo-terminals)")

    from estimator.models import resolve_model_dir
    from estimator.runtime import OnnxModel

    # Loaded here, as the rig will: a wrong --model is said at once, not as a rig that ended early.
    model = OnnxModel.load(resolve_model_dir(args.model))

    stop = threading.Event()
    drive = DemoStream()
    camera_cuts, gnss_cuts = Cuts(args.camera_drop_s, stop), Cuts(args.gnss_drop_s, stop)
    http = camera_server(drive, camera_cuts)
    listener = gnss_server(drive, gnss_cuts)
    master, slave = os.openpty()
    serial_counts = {"bytes": 0}
    threading.Thread(target=serial_reader, args=(master, args.serial_stall_s, stop, serial_counts),
                     name="serial-reader", daemon=True).start()

    out = Path(tempfile.mkdtemp(prefix="sunrig-soak-"))
    jsonl, stderr_path = out / "estimates.jsonl", out / "stderr.txt"
    cmd = [sys.executable, "-m", "rig.cli", "run",
           "--camera", f"opencv:http://127.0.0.1:{http.server_address[1]}/stream.mjpg",
           "--hfov-deg", "81.4",  # KITTI's fx = 721.5 px over 1242 px
           "--heading", f"nmea:socket://127.0.0.1:{listener.getsockname()[1]}",
           "--serial", os.ttyname(slave), "--jsonl", str(jsonl), "--record", str(out / "{start}.mcap")]
    if args.model:
        cmd += ["--model", args.model]
    # PYTHONFAULTHANDLER: a rig that does not stop after SIGTERM is sent SIGABRT, and dumps every
    # thread's stack into its stderr file, to show where it hangs.
    env = {**os.environ, "PYTHONPATH": str(Path(__file__).resolve().parent.parent), "PYTHONFAULTHANDLER": "1"}
    samples: list[dict] = []
    # SIGTERM (a shell's kill, a CI timeout) ends the benchmark through the except above, as Ctrl-C
    # does, so the rig it started does not outlive it.
    signal.signal(signal.SIGTERM, lambda *_: sys.exit(128 + signal.SIGTERM))
    with open(stderr_path, "w") as err:
        proc = subprocess.Popen(cmd, stdout=subprocess.DEVNULL, stderr=err, env=env)
        t0 = time.monotonic()
        end = t0 + 60.0 * args.minutes
        try:
            while time.monotonic() < end and proc.poll() is None:
                s = sample(proc.pid)
                if s is not None:
                    samples.append({"t_s": round(time.monotonic() - t0, 1), **s})
                time.sleep(SAMPLE_EVERY_S)
        except BaseException:  # Ctrl-C, or SIGTERM (above): stop the rig too, not leave it running
            stop_rig(proc, wait_s=10.0)
            # Nothing was measured to the end: its part-recording and JSONL are not worth keeping.
            shutil.rmtree(out, ignore_errors=True)
            raise
        ended_early = proc.poll() is not None
        t_int = time.monotonic()
        code = stop_rig(proc, wait_s=30.0)
        stop_s = time.monotonic() - t_int
    stop.set()
    http.shutdown()
    listener.close()

    from replay.native import read_estimates

    recordings = sorted(out.glob("*.mcap"))
    recorded = sum(1 for p in recordings for _ in read_estimates(p)) if recordings else 0
    lines = jsonl.read_text().splitlines() if jsonl.exists() else []
    after = [s for s in samples if s["t_s"] >= args.warmup_s]
    trend = slope_per_hour([s["t_s"] for s in after], [s["rss_mb"] for s in after])
    stderr_lines = stderr_path.read_text().splitlines()
    warnings = [line for line in stderr_lines if "WARNING" in line or "ERROR" in line]
    # What the rig said about each fault (one warning per outage), and anything else it warned of.
    kinds = ("camera", "GNSS", "serial")
    said = {kind: sum(kind in line for line in warnings) for kind in kinds}
    other = [line for line in warnings if not any(kind in line for kind in kinds)]
    stderr_tail = stderr_lines[-6:]

    def span(key: str) -> dict:
        values = [s[key] for s in after] or [s[key] for s in samples]
        return {"first": values[0], "last": values[-1], "min": min(values), "max": max(values)} if values else {}

    print(json.dumps({
        "benchmark": "soak",
        "minutes": args.minutes,
        "model": {"dir": str(model.model_dir), "id": model.model_id},
        "faults_every_s": {"camera_drop": args.camera_drop_s, "gnss_drop": args.gnss_drop_s,
                           "serial_stall_per_minute": args.serial_stall_s},
        "warmup_s": args.warmup_s,
        "command": " ".join(cmd[1:]),
        "ended_before_stop": ended_early,
        "exit_code": code,
        "stop_after_sigterm_s": round(stop_s, 2),
        "samples": len(samples),
        "rss_mb": span("rss_mb"),
        "rss_trend_mb_per_hour": None if trend is None else round(trend, 2),
        # One sample a minute: a trend that flattens is warm-up (allocator, arenas), one that holds is a leak.
        "rss_mb_by_minute": [round(s["rss_mb"], 1) for s in samples
                             if s["t_s"] >= SAMPLE_EVERY_S and s["t_s"] % 60.0 < SAMPLE_EVERY_S],
        "fds": span("fds"),
        "threads": span("threads"),
        "faults": {"camera_connections": camera_cuts.connections, "camera_cuts": camera_cuts.cuts,
                   "gnss_connections": gnss_cuts.connections, "gnss_cuts": gnss_cuts.cuts,
                   "serial_bytes_read": serial_counts["bytes"]},
        "rig_warnings": {**said, "other": len(other)},
        "rig_other_warnings": other[:10],
        "jsonl_lines": len(lines),
        "recordings": [p.name for p in recordings],
        "recorded_estimates": recorded,
        "rig_stderr_tail": stderr_tail,
        "output_folder": str(out),
        "machine": machine(),
    }, indent=2))


if __name__ == "__main__":
    run(main)
