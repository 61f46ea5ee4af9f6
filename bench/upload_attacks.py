"""Adversarial scene uploads against a live `fluidnexus serve`: memory and time to refuse (issue 20).

    python bench/upload_attacks.py [--rounds 3] [--json]

Starts `fluidnexus serve --no-worker` on 127.0.0.1 (embedded SQLite, `bench.load.live_server`),
then `--rounds` times sends six hostile uploads at once:
  - `png16k`: a 0.7 MB MOV holding one 16000x16000 PNG frame (768 MB as RGB) for a 270x480 camera;
  - `png16k_lying`: the same frame, its container header claiming 270x480;
  - `zip_bomb`: a 0.5 MB COLMAP zip whose points3D.txt unpacks to 500 MiB of zeros;
  - `zip_20k`: a 2.5 MB COLMAP zip of 20,000 `sparse/N/cameras.txt` members;
  - `images_821k`: a COLMAP zip whose images.txt lists 821,732 images (issue 36: 285 s, 1.28 GB);
  - `images_bin_1e9`: a COLMAP zip whose images.bin declares 1e9 images (issue 36: HTTP 500).
Reported per upload: status, seconds to the answer, the answer's message; and the server's peak
resident memory (VmHWM of its process, `--no-worker`) before and after, and that of each upload
validation process below it (api.uploads.Validators). Targets: every upload refused (4xx) within
2 s, server peak RSS <= 512 MB.
"""

from __future__ import annotations

import json
import struct
import sys
import tempfile
import time
import zipfile
import zlib
from concurrent.futures import ThreadPoolExecutor
from fractions import Fraction
from pathlib import Path
from typing import Any

import typer

if __package__ in (None, ""):  # `python bench/upload_attacks.py`
    sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from bench.load import camera_json, live_server  # noqa: E402
from fluidnexus.reporting import echo_json, user_errors  # noqa: E402

CAMERA = (270, 480)  # width, height of the dev scene's views, the camera the hostile video claims
REFUSE_WITHIN_S = 2.0
PEAK_RSS_MB = 512.0
Parts = list[tuple[str, tuple[str, bytes, str]]]


def png_bytes(width: int, height: int) -> bytes:
    """A black RGB PNG of any size, compressed row by row: a 16000x16000 one is 0.7 MB and is
    built in a few MB of memory (the decoder needs 768 MB for it)."""

    def chunk(kind: bytes, data: bytes) -> bytes:
        return struct.pack(">I", len(data)) + kind + data + struct.pack(">I", zlib.crc32(kind + data))

    packer, row = zlib.compressobj(9), bytes(1 + 3 * width)  # filter byte + RGB
    pixels = b"".join(packer.compress(row) for _ in range(height)) + packer.flush()
    header = struct.pack(">IIBBBBB", width, height, 8, 2, 0, 0, 0)
    return b"\x89PNG\r\n\x1a\n" + chunk(b"IHDR", header) + chunk(b"IDAT", pixels) + chunk(b"IEND", b"")


def png_mov(path: Path, frame: tuple[int, int], declared: tuple[int, int] | None = None) -> Path:
    """A MOV with one PNG frame of `frame` (width, height) pixels whose header declares
    `declared` (default: the true size), muxed without decoding or encoding anything."""
    import av

    with av.open(str(path), "w", format="mov") as container:
        stream = container.add_stream("png", rate=30)
        stream.codec_context.width, stream.codec_context.height = declared or frame
        stream.codec_context.pix_fmt = "rgb24"
        packet = av.Packet(png_bytes(*frame))
        packet.stream, packet.pts, packet.dts, packet.time_base = stream, 0, 0, Fraction(1, 30)
        container.mux(packet)
    return path


def zip_bomb(path: Path, unpacked_bytes: int) -> Path:
    """A COLMAP-looking zip whose points3D.txt is `unpacked_bytes` of zeros (about 1/1000 of it packed)."""
    with zipfile.ZipFile(path, "w", zipfile.ZIP_DEFLATED, compresslevel=9) as archive:
        archive.writestr("sparse/0/cameras.txt", "1 PINHOLE 270 480 300 300 135 240\n")
        archive.writestr("sparse/0/images.txt", "1 1 0 0 0 0 0 4 1 view.png\n\n")
        with archive.open("sparse/0/points3D.txt", "w", force_zip64=True) as member:
            block = bytes(1 << 20)
            for _ in range(unpacked_bytes >> 20):
                member.write(block)
    return path


def many_images_zip(path: Path, images: int) -> Path:
    """A COLMAP text model in a zip whose images.txt lists `images` posed images of one camera
    (the issue 36 probe: 821,732 of them in 3.8 MB)."""
    with zipfile.ZipFile(path, "w", zipfile.ZIP_DEFLATED, compresslevel=9) as archive:
        archive.writestr("sparse/0/cameras.txt", "1 PINHOLE 270 480 300 300 135 240\n")
        with archive.open("sparse/0/images.txt", "w") as member:
            for index in range(1, images + 1):
                member.write(f"{index} 1 0 0 0 0 0 4 1 view{index}.png\n\n".encode())
        archive.writestr("sparse/0/points3D.txt", "")
    return path


def declared_images_zip(path: Path, declared: int) -> Path:
    """A COLMAP binary model in a zip whose images.bin declares `declared` images and holds none."""
    cameras = struct.pack("<Q", 1) + struct.pack("<iiQQ", 1, 1, 270, 480) + struct.pack("<4d", 300, 300, 135, 240)
    with zipfile.ZipFile(path, "w") as archive:
        archive.writestr("sparse/0/cameras.bin", cameras)
        archive.writestr("sparse/0/images.bin", struct.pack("<Q", declared))
        archive.writestr("sparse/0/points3D.bin", struct.pack("<Q", 0))
    return path


def many_member_zip(path: Path, members: int) -> Path:
    """A zip of `members` tiny `sparse/N/cameras.txt` files."""
    with zipfile.ZipFile(path, "w", zipfile.ZIP_DEFLATED) as archive:
        for index in range(members):
            archive.writestr(f"sparse/{index}/cameras.txt", "1 PINHOLE 270 480 300 300 135 240\n")
    return path


def attacks(folder: Path) -> dict[str, Parts]:
    """The hostile uploads as multipart parts for POST /v1/scenes."""
    import numpy as np

    from fluidcore.video import write_mp4

    cameras = ("cameras", ("transforms.json", camera_json("view", *CAMERA), "application/json"))
    small = write_mp4(folder / "view.mp4", np.zeros((2, CAMERA[1], CAMERA[0], 3), np.uint8))
    video = ("video", ("view.mp4", small.read_bytes(), "video/mp4"))

    def mov(name: str, declared: tuple[int, int] | None) -> Parts:
        data = png_mov(folder / f"{name}.mov", (16000, 16000), declared).read_bytes()
        return [cameras, ("video", ("view.mov", data, "video/quicktime"))]

    def colmap(path: Path) -> Parts:
        return [("cameras", ("cameras.zip", path.read_bytes(), "application/zip")), video]

    return {
        "png16k": mov("png16k", None),
        "png16k_lying": mov("png16k_lying", CAMERA),
        "zip_bomb": colmap(zip_bomb(folder / "bomb.zip", 500 << 20)),
        "zip_20k": colmap(many_member_zip(folder / "many.zip", 20_000)),
        "images_821k": colmap(many_images_zip(folder / "images.zip", 821_732)),
        "images_bin_1e9": colmap(declared_images_zip(folder / "declared.zip", 10**9)),
    }


def descendants(pid: int) -> list[int]:
    """Processes below `pid` (the server's upload validators), from /proc."""
    found = []
    for task in Path(f"/proc/{pid}/task").iterdir():
        for child in (task / "children").read_text().split():
            found += [int(child), *descendants(int(child))]
    return found


def peak_rss_mb(pid: int) -> float:
    """VmHWM (peak resident set) of a process, MB."""
    for line in Path(f"/proc/{pid}/status").read_text().splitlines():
        if line.startswith("VmHWM:"):
            return int(line.split()[1]) / 1024
    raise RuntimeError(f"no VmHWM for process {pid}")


def run_attacks(rounds: int) -> dict[str, Any]:
    import httpx

    results: list[dict[str, Any]] = []
    with tempfile.TemporaryDirectory(prefix="fluidnexus-attacks-") as tmp, live_server("sqlite") as server:
        uploads = attacks(Path(tmp))
        baseline = peak_rss_mb(server.pid)
        headers = {"Authorization": f"Bearer {server.key}"}

        def send(name: str) -> dict[str, Any]:
            with httpx.Client(base_url=server.base_url, headers=headers, timeout=120) as client:
                start = time.perf_counter()
                answer = client.post("/v1/scenes", files=uploads[name])
                seconds = time.perf_counter() - start
            return {"upload": name, "status": answer.status_code, "seconds": seconds, "detail": answer.text[:300]}

        for round_index in range(rounds):
            with ThreadPoolExecutor(len(uploads)) as pool:
                for result in pool.map(send, uploads):
                    results.append({"round": round_index, **result})
        peak = peak_rss_mb(server.pid)
        validators = {pid: peak_rss_mb(pid) for pid in descendants(server.pid)}
    return {
        "rounds": rounds,
        "server_peak_rss_mb_before": baseline,
        "server_peak_rss_mb": peak,
        "validator_peak_rss_mb": validators,
        "total_peak_rss_mb": peak + sum(validators.values()),
        "slowest_s": max(r["seconds"] for r in results),
        "all_refused": all(400 <= r["status"] < 500 for r in results),
        "targets": {"refused_within_s": REFUSE_WITHIN_S, "peak_rss_mb": PEAK_RSS_MB},
        "uploads": results,
    }


def command(
    rounds: int = typer.Option(3, "--rounds", min=1, max=20, help="Times the four uploads are sent at once."),
    json_out: bool = typer.Option(False, "--json", help="Print one JSON object on stdout."),
) -> None:
    with user_errors():
        result = run_attacks(rounds)
    if json_out:
        echo_json(result)
        return
    print(f"{'upload':<14} {'round':>5} {'status':>6} {'seconds':>8}  message")
    for r in result["uploads"]:
        message = json.loads(r["detail"]).get("detail", "") if r["detail"].startswith("{") else r["detail"]
        print(f"{r['upload']:<14} {r['round']:5d} {r['status']:6d} {r['seconds']:8.3f}  {str(message)[:90]}")
    validators = ", ".join(f"{mb:.0f}" for mb in result["validator_peak_rss_mb"].values())
    print(f"validation processes' peak RSS: {validators} MB; server + validators {result['total_peak_rss_mb']:.0f} MB")
    print(f"server peak RSS {result['server_peak_rss_mb']:.0f} MB (at start {result['server_peak_rss_mb_before']:.0f} MB), "
          f"slowest answer {result['slowest_s']:.2f} s, all refused: {result['all_refused']}")


if __name__ == "__main__":
    from bench.registry import run_script

    run_script("upload_attacks", command)
