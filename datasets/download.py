#!/usr/bin/env python3
"""Fetch the full public benchmarks into the layout vslam's readers open.

    python datasets/download.py tum fr3_walking_xyz fr3_sitting_static --dest DIR
    python datasets/download.py euroc V1_01_easy --dest DIR [--mirror legacy]
    python datasets/download.py kitti                        # prints the registration steps
    python datasets/download.py kitti --zip data_odometry_gray.zip --zip data_odometry_poses.zip \\
        --zip data_odometry_calib.zip --dest DIR             # unpacks zips you downloaded
    python datasets/download.py tum fr3_walking_xyz --dry-run   # prints URLs, touches nothing

Results land in DIR/tum/<rgbd_dataset_...>, DIR/euroc/<sequence>/mav0, DIR/kitti/{sequences,poses}
(DIR defaults to datasets/raw, which git ignores). Downloads resume from a ``.part`` file
after an interruption (HTTP Range). No checksums are published for these archives; instead
every extracted sequence is opened with vslam's reader, which checks its whole layout.

Standard library only (urllib). Exit codes: 0 ok, 1 download/layout error, 2 usage.
"""

from __future__ import annotations

import argparse
import re
import shutil
import sys
import tarfile
import tempfile
import time
import urllib.error
import urllib.request
import zipfile
from collections.abc import Sequence as Seq
from pathlib import Path
from typing import Any

REPO_ROOT = Path(__file__).resolve().parent.parent
DEFAULT_DEST = REPO_ROOT / "datasets" / "raw"
USER_AGENT = "vslam-datasets/0.1 (python urllib)"

# ------------------------------------------------------------------------------- URL tables

TUM_BASE = "https://cvg.cit.tum.de/rgbd/dataset"
TUM_SEQUENCES: tuple[str, ...] = (
    "freiburg1_xyz", "freiburg1_rpy", "freiburg1_360", "freiburg1_floor", "freiburg1_desk", "freiburg1_desk2",
    "freiburg1_room", "freiburg1_plant", "freiburg1_teddy",
    "freiburg2_xyz", "freiburg2_rpy", "freiburg2_360_hemisphere", "freiburg2_360_kidnap", "freiburg2_desk",
    "freiburg2_desk_with_person", "freiburg2_large_no_loop", "freiburg2_large_with_loop", "freiburg2_pioneer_360",
    "freiburg2_pioneer_slam", "freiburg2_pioneer_slam2", "freiburg2_pioneer_slam3",
    "freiburg3_long_office_household", "freiburg3_teddy", "freiburg3_cabinet", "freiburg3_large_cabinet",
    "freiburg3_structure_texture_far", "freiburg3_structure_texture_near", "freiburg3_nostructure_texture_far",
    "freiburg3_structure_notexture_far", "freiburg3_structure_notexture_near",
    "freiburg3_sitting_static", "freiburg3_sitting_xyz", "freiburg3_sitting_halfsphere", "freiburg3_sitting_rpy",
    "freiburg3_walking_static", "freiburg3_walking_xyz", "freiburg3_walking_halfsphere", "freiburg3_walking_rpy",
)

# EuRoC: since robotics.ethz.ch retired, the official host is the ETH Research Collection
# record https://www.research-collection.ethz.ch/handle/20.500.11850/690084
# (DOI 10.3929/ethz-b-000690084), one zip per room holding a zip per sequence.
EUROC_RECORD = "https://www.research-collection.ethz.ch/handle/20.500.11850/690084"
EUROC_BITSTREAM = "https://www.research-collection.ethz.ch/server/api/core/bitstreams/{uuid}/content"
EUROC_ARCHIVES: dict[str, str] = {  # room archive -> bitstream id on the record page
    "machine_hall": "7b2419c1-62b5-4714-b7f8-485e5fe3e5fe",
    "vicon_room1": "02ecda9a-298f-498b-970c-b7c44334d880",
    "vicon_room2": "ea12bc01-3677-4b4c-853d-87c7870b8c44",
}
EUROC_LEGACY = "http://robotics.ethz.ch/~asl-datasets/ijrr_euroc_mav_dataset/{room}/{seq}/{seq}.zip"
EUROC_SEQUENCES: dict[str, str] = {
    "MH_01_easy": "machine_hall", "MH_02_easy": "machine_hall", "MH_03_medium": "machine_hall",
    "MH_04_difficult": "machine_hall", "MH_05_difficult": "machine_hall",
    "V1_01_easy": "vicon_room1", "V1_02_medium": "vicon_room1", "V1_03_difficult": "vicon_room1",
    "V2_01_easy": "vicon_room2", "V2_02_medium": "vicon_room2", "V2_03_difficult": "vicon_room2",
}

KITTI_PAGE = "https://www.cvlibs.net/datasets/kitti/eval_odometry.php"
KITTI_FILES = {
    "data_odometry_gray.zip": "grey stereo image_0/image_1, 22 GB",
    "data_odometry_color.zip": "colour stereo image_2/image_3, 65 GB (optional)",
    "data_odometry_calib.zip": "calib.txt + times.txt per sequence",
    "data_odometry_poses.zip": "ground-truth poses 00-10",
}


class FetchError(RuntimeError):
    """A download or extraction cannot go on; the message says why."""


def tum_name(name: str) -> str:
    """'fr3_walking_xyz' / 'freiburg3_walking_xyz' / 'rgbd_dataset_freiburg3_walking_xyz' -> 'freiburg3_walking_xyz'."""
    n = name.strip().lower().removeprefix("rgbd_dataset_")
    n = re.sub(r"^fr([123])_", r"freiburg\1_", n)
    if not re.fullmatch(r"freiburg[123]_[a-z0-9_]+", n):
        raise FetchError(f"{name!r} is not a TUM RGB-D sequence name (e.g. fr3_walking_xyz)")
    return n


def tum_url(name: str) -> str:
    n = tum_name(name)
    return f"{TUM_BASE}/{n[:9]}/rgbd_dataset_{n}.tgz"


def euroc_url(seq: str, mirror: str = "research-collection") -> str:
    if seq not in EUROC_SEQUENCES:
        raise FetchError(f"unknown EuRoC sequence {seq!r}; known: {', '.join(EUROC_SEQUENCES)}")
    room = EUROC_SEQUENCES[seq]
    if mirror == "legacy":
        return EUROC_LEGACY.format(room=room, seq=seq)
    return EUROC_BITSTREAM.format(uuid=EUROC_ARCHIVES[room])


def url_table() -> dict[str, str]:
    """Every known download URL by '<dataset>/<sequence>' (no network)."""
    table = {f"tum/{n}": tum_url(n) for n in TUM_SEQUENCES}
    table.update({f"euroc/{s}": euroc_url(s) for s in EUROC_SEQUENCES})
    table.update({f"euroc-legacy/{s}": euroc_url(s, "legacy") for s in EUROC_SEQUENCES})
    return table


# ------------------------------------------------------------------------------- download


def log(msg: str) -> None:
    print(msg, file=sys.stderr, flush=True)


def fetch(url: str, target: Path, attempts: int = 5) -> Path:
    """Download url to target, resuming ``target.part`` with an HTTP Range request; skip if target exists."""
    if target.is_file():
        log(f"have {target}")
        return target
    target.parent.mkdir(parents=True, exist_ok=True)
    part = target.with_name(target.name + ".part")
    for attempt in range(1, attempts + 1):
        have = part.stat().st_size if part.is_file() else 0
        headers = {"User-Agent": USER_AGENT, **({"Range": f"bytes={have}-"} if have else {})}
        try:
            with urllib.request.urlopen(urllib.request.Request(url, headers=headers), timeout=60) as resp:
                resume = have > 0 and resp.status == 206
                total = int(resp.headers.get("Content-Length") or 0) + (have if resume else 0)
                log(f"{'resuming' if resume else 'fetching'} {url} -> {target} ({total / 1e9:.2f} GB)")
                with open(part, "ab" if resume else "wb") as out:
                    _copy(resp, out, have if resume else 0, total)
            part.replace(target)
            return target
        except urllib.error.HTTPError as exc:
            if exc.code == 416 and have:  # the .part already holds the whole file
                part.replace(target)
                return target
            if exc.code not in (429, 500, 502, 503, 504) or attempt == attempts:
                raise FetchError(f"{url}: HTTP {exc.code} {exc.reason}") from None
        except (urllib.error.URLError, TimeoutError, ConnectionError) as exc:
            if attempt == attempts:
                raise FetchError(f"{url}: {exc} (run again to resume from {part})") from None
        wait = 2.0**attempt
        log(f"transient error, retrying in {wait:.0f} s ({attempt}/{attempts})")
        time.sleep(wait)
    raise FetchError(f"{url}: gave up")


def _copy(resp: object, out: object, done: int, total: int) -> None:
    last = time.monotonic()
    while chunk := resp.read(1 << 20):  # type: ignore[attr-defined]
        out.write(chunk)  # type: ignore[attr-defined]
        done += len(chunk)
        if time.monotonic() - last > 5:
            last = time.monotonic()
            log(f"  {done / 1e9:.2f} / {total / 1e9:.2f} GB")


# ------------------------------------------------------------------------------- extraction


def extract_tgz(archive: Path, dest: Path) -> None:
    with tarfile.open(archive) as tf:
        if hasattr(tarfile, "data_filter"):
            tf.extractall(dest, filter="data")  # blocks absolute paths, '..' and links out of dest
            return
        for m in tf.getmembers():  # Python < 3.10.12 / 3.11.4: check by hand
            if Path(m.name).is_absolute() or ".." in Path(m.name).parts or m.issym() or m.islnk():
                raise FetchError(f"{archive}: unsafe member {m.name!r}")
        tf.extractall(dest)


def extract_mav0(zf: zipfile.ZipFile, seq: str, dest: Path) -> bool:
    """Copy every '<...>/mav0/...' member of zf to dest/seq/mav0/...; False if there is none.

    In a room zip that holds several sequences unpacked, only members with
    ``seq`` among the folders before ``mav0/`` are taken.
    """
    picked: list[tuple[zipfile.ZipInfo, str]] = []
    for m in zf.infolist():
        name = m.filename
        if m.is_dir() or "__MACOSX" in name or not re.search(r"(^|/)mav0/", name):
            continue
        prefix, rel = re.split(r"(?:^|/)mav0/", name, maxsplit=1)
        parts = [p for p in prefix.split("/") if p]
        if parts and seq not in parts:
            continue
        if ".." in Path(rel).parts:
            raise FetchError(f"unsafe member name {name!r}")
        picked.append((m, f"mav0/{rel}"))
    for m, rel in picked:
        out = dest / seq / rel
        out.parent.mkdir(parents=True, exist_ok=True)
        with zf.open(m) as src, open(out, "wb") as dst:
            shutil.copyfileobj(src, dst, 1 << 20)
    return bool(picked)


def extract_euroc(archive: Path, seq: str, dest: Path) -> None:
    """A per-sequence zip (mav0/ inside) or a room zip holding '<seq>.zip' or '<seq>/mav0/'."""
    with zipfile.ZipFile(archive) as zf:
        if extract_mav0(zf, seq, dest):
            return
        nested = [m for m in zf.infolist() if Path(m.filename).name == f"{seq}.zip"]
        if len(nested) != 1:
            raise FetchError(f"{archive}: holds neither {seq}/mav0/ nor one {seq}.zip")
        with tempfile.TemporaryDirectory(dir=dest) as tmp:
            inner = Path(zf.extract(nested[0], tmp))
            with zipfile.ZipFile(inner) as zin:
                if not extract_mav0(zin, seq, dest):
                    raise FetchError(f"{archive}!{nested[0].filename}: no mav0/ inside")


def extract_kitti(archive: Path, dest: Path) -> None:
    """KITTI zips hold 'dataset/sequences/NN/...' and 'dataset/poses/NN.txt'; drop the 'dataset/'."""
    with zipfile.ZipFile(archive) as zf:
        for m in zf.infolist():
            rel = m.filename.removeprefix("dataset/")
            if m.is_dir() or ".." in Path(rel).parts or not rel.startswith(("sequences/", "poses/")):
                continue
            out = dest / rel
            out.parent.mkdir(parents=True, exist_ok=True)
            with zf.open(m) as src, open(out, "wb") as dst:
                shutil.copyfileobj(src, dst, 1 << 20)


def verify(path: Path, **options: Any) -> None:
    """Open the extracted sequence with vslam's reader: the layout check the archives lack."""
    sys.path.insert(0, str(REPO_ROOT))
    from vslam.data.registry import open_sequence
    from vslam.errors import VslamError

    try:
        seq = open_sequence(path, **options)
    except VslamError as exc:
        raise FetchError(f"layout check failed: {exc}") from None
    t = seq.timestamps()
    span = float(t[-1] - t[0]) if len(t) else 0.0
    gt = seq.groundtruth()
    log(f"ok {path}: {len(seq)} frames, {span:.1f} s, ground truth: {len(gt) if gt is not None else 'none'} poses")


# ------------------------------------------------------------------------------- commands


def cmd_tum(names: Seq[str], dest: Path, dry_run: bool) -> None:
    for name in names:
        n = tum_name(name)
        if n not in TUM_SEQUENCES:
            log(f"warning: {n} is not in the known list; trying {tum_url(n)} anyway")
        url, folder = tum_url(n), dest / "tum" / f"rgbd_dataset_{n}"
        print(f"{url} -> {folder}")
        if dry_run:
            continue
        if not (folder / "rgb.txt").is_file():
            archive = fetch(url, dest / "downloads" / Path(url).name)
            extract_tgz(archive, folder.parent)
        verify(folder)


def cmd_euroc(names: Seq[str], dest: Path, dry_run: bool, mirror: str) -> None:
    for seq in names:
        url, folder = euroc_url(seq, mirror), dest / "euroc" / seq
        print(f"{url} -> {folder}")
        if dry_run:
            continue
        if not (folder / "mav0").is_dir():
            name = f"{seq}.zip" if mirror == "legacy" else f"{EUROC_SEQUENCES[seq]}.zip"
            archive = fetch(url, dest / "downloads" / name)
            folder.parent.mkdir(parents=True, exist_ok=True)
            extract_euroc(archive, seq, folder.parent)
        verify(folder)


def cmd_kitti(zips: Seq[str], dest: Path, dry_run: bool, sequence: str) -> None:
    if not zips:
        print(
            f"KITTI odometry needs a (free) registration, so it cannot be fetched by script.\n"
            f"1. Register and log in at {KITTI_PAGE}\n"
            "2. Download (links on that page):\n"
            + "".join(f"     {k:26s} {v}\n" for k, v in KITTI_FILES.items())
            + f"3. python datasets/download.py kitti --zip data_odometry_gray.zip --zip data_odometry_calib.zip "
            f"--zip data_odometry_poses.zip --dest {dest}"
        )
        return
    for z in zips:
        print(f"{z} -> {dest / 'kitti'}")
        if not dry_run:
            extract_kitti(Path(z), dest / "kitti")
    if not dry_run:
        verify(dest / "kitti", sequence=sequence)


def build_parser() -> argparse.ArgumentParser:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0], formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("dataset", choices=("tum", "euroc", "kitti"))
    ap.add_argument("names", nargs="*", help="sequences: tum fr3_walking_xyz ..., euroc V1_01_easy ...")
    ap.add_argument("--dest", type=Path, default=DEFAULT_DEST, help=f"root folder (default {DEFAULT_DEST})")
    ap.add_argument("--dry-run", action="store_true", help="print URLs and targets; no network, no files")
    ap.add_argument("--list", action="store_true", help="print the known sequences and their URLs")
    ap.add_argument("--mirror", choices=("research-collection", "legacy"), default="research-collection",
                    help="EuRoC host: the ETH Research Collection room archives, or the retired per-sequence robotics.ethz.ch zips")
    ap.add_argument("--zip", action="append", default=[], help="kitti: a downloaded KITTI zip to unpack (repeatable)")
    ap.add_argument("--sequence", default="00", help="kitti: sequence opened to verify the unpacked layout")
    return ap


def main(argv: Seq[str] | None = None) -> int:
    parser = build_parser()
    args = parser.parse_args(argv)
    if args.dataset in ("tum", "euroc") and not args.names and not args.list:
        parser.error(f"name at least one {args.dataset} sequence (see --list)")
    try:
        if args.list:
            for key, url in url_table().items():
                if key.split("/")[0].startswith(args.dataset):
                    print(f"{key:50s} {url}")
            return 0
        if args.dataset == "tum":
            cmd_tum(args.names, args.dest, args.dry_run)
        elif args.dataset == "euroc":
            cmd_euroc(args.names, args.dest, args.dry_run, args.mirror)
        else:
            cmd_kitti(args.zip, args.dest, args.dry_run, args.sequence)
    except FetchError as exc:
        log(f"error: {exc}")
        return 1
    return 0


if __name__ == "__main__":
    sys.exit(main())
