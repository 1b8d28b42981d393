"""A real HTTP server on 127.0.0.1 (the standard library's, with range requests) and fixture archives in
the upstream archives' exact layouts: the 3DMatch toolbox's per-scene zips, 3DLoMatch's gt.log tree,
KITTI odometry's three zips. The clouds are small (synthetic rooms, registrable under their GT)."""

from __future__ import annotations

import io
import re
import socket
import threading
import zipfile
from http.server import BaseHTTPRequestHandler, ThreadingHTTPServer
from pathlib import Path

import numpy as np
import yaml

from fastmac_exp.datasets.mac_layout import SCENES_3DMATCH
from fastmac_exp.datasets.synthetic import default_config, generate_pair


class FixtureServer:
    """Serves `files` (URL path -> bytes). Switches: `ranges` (False: a Range header is ignored and the
    whole file comes with 200), `cut` (URL path -> byte count: each of the next `cuts[path]` responses
    stops after that many bytes of the body and drops the connection), `missing` (paths answering 404).
    `served[path]` counts the body bytes sent."""

    def __init__(self) -> None:
        self.files: dict[str, bytes] = {}
        self.ranges = True
        self.cut: dict[str, int] = {}
        self.cuts: dict[str, int] = {}
        self.missing: set[str] = set()
        self.served: dict[str, int] = {}
        self.requests: list[tuple[str, str, str | None]] = []
        server = self

        class Handler(BaseHTTPRequestHandler):
            protocol_version = "HTTP/1.1"

            def log_message(self, *args) -> None:
                pass

            def do_HEAD(self) -> None:
                self._answer(body=False)

            def do_GET(self) -> None:
                self._answer(body=True)

            def _answer(self, body: bool) -> None:
                path = self.path.split("?")[0]
                rng = self.headers.get("Range")
                server.requests.append((self.command, path, rng))
                data = server.files.get(path)
                if data is None or path in server.missing:
                    self.send_response(404)
                    self.send_header("Content-Length", "0")
                    self.end_headers()
                    return
                start, end, status = 0, len(data) - 1, 200
                m = re.fullmatch(r"bytes=(\d*)-(\d*)", rng or "") if server.ranges else None
                if m:
                    a, b = m.groups()
                    if a == "":
                        start = max(0, len(data) - int(b))
                    else:
                        start, end = int(a), min(int(b), len(data) - 1) if b else len(data) - 1
                    if start >= len(data):
                        self.send_response(416)
                        self.send_header("Content-Range", f"bytes */{len(data)}")
                        self.send_header("Content-Length", "0")
                        self.end_headers()
                        return
                    status = 206
                chunk = data[start : end + 1]
                self.send_response(status)
                self.send_header("Content-Length", str(len(chunk)))
                self.send_header("Accept-Ranges", "bytes" if server.ranges else "none")
                if status == 206:
                    self.send_header("Content-Range", f"bytes {start}-{end}/{len(data)}")
                self.end_headers()
                if not body:
                    return
                if server.cuts.get(path, 0) > 0:
                    server.cuts[path] -= 1
                    chunk = chunk[: server.cut[path]]
                    # counted before the write: the client may have read it all before this thread runs on
                    server.served[path] = server.served.get(path, 0) + len(chunk)
                    self.wfile.write(chunk)
                    self.wfile.flush()
                    self.close_connection = True
                    self.connection.shutdown(socket.SHUT_WR)  # the bytes sent arrive, then EOF
                    return
                server.served[path] = server.served.get(path, 0) + len(chunk)
                self.wfile.write(chunk)

        self.httpd = ThreadingHTTPServer(("127.0.0.1", 0), Handler)
        self.httpd.daemon_threads = True
        self.thread = threading.Thread(target=self.httpd.serve_forever, daemon=True)

    @property
    def base(self) -> str:
        return f"http://127.0.0.1:{self.httpd.server_address[1]}"

    def __enter__(self) -> FixtureServer:
        self.thread.start()
        return self

    def __exit__(self, *exc) -> None:
        self.httpd.shutdown()
        self.httpd.server_close()


# -- fixture archives ---------------------------------------------------------------------------------------
def ply_bytes(xyz: np.ndarray) -> bytes:
    head = (
        f"ply\nformat binary_little_endian 1.0\nelement vertex {len(xyz)}\n"
        "property float x\nproperty float y\nproperty float z\nend_header\n"
    )
    return head.encode() + np.ascontiguousarray(xyz, dtype="<f4").tobytes()


def gt_log(entries: list[tuple[int, int, int, np.ndarray]]) -> bytes:
    lines = []
    for i, j, n, t in entries:
        lines.append(f"{i}\t{j}\t{n}")
        lines += ["\t".join(f"{v:.12f}" for v in row) for row in t]
    return ("\n".join(lines) + "\n").encode()


def zip_bytes(members: dict[str, bytes], method: int = zipfile.ZIP_DEFLATED) -> bytes:
    buf = io.BytesIO()
    with zipfile.ZipFile(buf, "w", method) as zf:
        for name, data in members.items():
            zf.writestr(name, data)
    return buf.getvalue()


def threedmatch_archives(points: int = 10000) -> dict[str, bytes]:
    """The toolbox's per-scene zips: <scene>.zip holds <scene>/cloud_bin_{0,1}.ply, <scene>-evaluation.zip
    holds <scene>-evaluation/gt.log (entry `0 1 2`: T maps cloud_bin_1, the source, into cloud_bin_0)
    and gt.info. One synthetic room pair per scene, high overlap, so FPFH + MAC register it."""
    cfg = default_config("3dmatch", points_per_scan=points, overlap_min=0.7, overlap_max=0.9, noise_scale=0.2)
    out = {}
    for k, scene in enumerate(SCENES_3DMATCH):
        pair = generate_pair(cfg, 11, k)
        out[f"{scene}.zip"] = zip_bytes(
            {
                f"{scene}/cloud_bin_0.ply": ply_bytes(pair["tgt"]),
                f"{scene}/cloud_bin_1.ply": ply_bytes(pair["src"]),
            }
        )
        info = "0\t1\t2\n" + "\n".join("\t".join(["1.0"] * 6) for _ in range(6)) + "\n"
        out[f"{scene}-evaluation.zip"] = zip_bytes(
            {
                f"{scene}-evaluation/gt.log": gt_log([(0, 1, 2, pair["gt"])]),
                f"{scene}-evaluation/gt.info": info.encode(),
            }
        )
    return out


def lomatch_files(archives: dict[str, bytes]) -> dict[str, bytes]:
    """3DLoMatch's tree <scene>/gt.log (+ gt.info), here the same entry as the 3DMatch log."""
    out = {}
    for scene in SCENES_3DMATCH:
        with zipfile.ZipFile(io.BytesIO(archives[f"{scene}-evaluation.zip"])) as zf:
            out[f"{scene}/gt.log"] = zf.read(f"{scene}-evaluation/gt.log")
            out[f"{scene}/gt.info"] = zf.read(f"{scene}-evaluation/gt.info")
    return out


def kitti_archives(frames: int = 14, step: float = 2.0, points: int = 1200) -> dict[str, bytes]:
    """KITTI odometry's zips: dataset/poses/<seq>.txt (00-10), dataset/sequences/<seq>/calib.txt and
    times.txt, dataset/sequences/<seq>/velodyne/<frame>.bin; a straight drive of `step` m a frame."""
    rng = np.random.default_rng(3)
    poses, calib, velo = {}, {}, {}
    tr = "Tr: " + " ".join(f"{v:.6e}" for v in np.eye(4)[:3].ravel())
    for seq in range(11):
        rows = []
        for f in range(frames):
            p = np.eye(4)[:3]
            p[2, 3] = step * f
            rows.append(" ".join(f"{v:.6e}" for v in p.ravel()))
        poses[f"dataset/poses/{seq:02d}.txt"] = ("\n".join(rows) + "\n").encode()
        calib[f"dataset/sequences/{seq:02d}/calib.txt"] = f"P0: {' '.join(['0'] * 12)}\n{tr}\n".encode()
        calib[f"dataset/sequences/{seq:02d}/times.txt"] = b"0.0\n"
        for f in range(frames):
            scan = np.c_[rng.uniform(-40, 40, (points, 3)), rng.uniform(0, 1, points)].astype("<f4")
            velo[f"dataset/sequences/{seq:02d}/velodyne/{f:06d}.bin"] = scan.tobytes()
    return {
        "data_odometry_poses.zip": zip_bytes(poses),
        "data_odometry_calib.zip": zip_bytes(calib),
        "data_odometry_velodyne.zip": zip_bytes(velo, zipfile.ZIP_STORED),
    }  # scans stored, as KITTI stores them


def sources_file(path: Path, mirrors: dict[str, list[str]], datasets: dict | None = None) -> Path:
    """A $FASTMAC_DATA_SOURCES file replacing the built-in mirror groups (and data sets) given."""
    path.write_text(yaml.safe_dump({"mirrors": mirrors, "datasets": datasets or {}}))
    return path
