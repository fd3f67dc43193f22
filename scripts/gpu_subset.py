"""Copy what a GPU-machine run of ``vslam train detector`` and the ``network-speed-gpu`` bench row read into a
compact folder that fits the device's 64 MiB transfer (the checkout's ``../shared/data`` does not travel there).

    python scripts/gpu_subset.py device_data          # then VSLAM_DATA=device_data on the GPU machine

What it holds: COCO128 train2017 (images re-encoded as JPEG quality 90, labels, person polygons); the training
frames of TUM fr3/teddy (0-99) and EuRoC V1_01 cam0 (0-47) that the detector's copy-paste uses as backgrounds,
every 2nd one as JPEG quality 92 and the others as empty placeholders, so that the recipe's "every 2nd of the
first N frames" picks exactly the frames it picks from the full data (an empty file reads as no image and is
skipped); TUM's rgb.txt lists the real frames only (the speed row's frames). The JPEG re-encoding is the one
difference from training on ../shared/data (model cards say so).
"""

from __future__ import annotations

import argparse
import shutil
import sys
from pathlib import Path

import cv2


def _jpeg(src: Path, dst: Path, quality: int) -> None:
    img = cv2.imread(str(src), cv2.IMREAD_UNCHANGED)
    if img is None:
        sys.exit(f"{src}: not a readable image")
    dst.parent.mkdir(parents=True, exist_ok=True)
    cv2.imwrite(str(dst), img, [cv2.IMWRITE_JPEG_QUALITY, quality])


def _frames(src_dir: Path, dst_dir: Path, n: int, quality: int) -> list[Path]:
    """Frames 0..n-1 in name order: even ones as JPEG, odd ones as empty placeholders. -> the JPEG paths."""
    files = sorted(p for p in src_dir.iterdir() if p.suffix.lower() in (".png", ".jpg"))[:n]
    dst_dir.mkdir(parents=True, exist_ok=True)
    real = []
    for i, f in enumerate(files):
        if i % 2 == 0:
            _jpeg(f, dst_dir / (f.stem + ".jpg"), quality)
            real.append(dst_dir / (f.stem + ".jpg"))
        else:
            (dst_dir / f.name).write_bytes(b"")
    return real


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("out", type=Path)
    ap.add_argument("--data", type=Path, default=Path(__file__).resolve().parents[1].parent / "shared" / "data")
    a = ap.parse_args()
    if a.out.exists():
        shutil.rmtree(a.out)
    coco, out_coco = a.data / "coco128", a.out / "coco128"
    for img in sorted((coco / "images" / "train2017").glob("*.jpg")):
        _jpeg(img, out_coco / "images" / "train2017" / img.name, 90)
    for sub in ("labels", "segments"):
        shutil.copytree(coco / sub / "train2017", out_coco / sub / "train2017")
    for f in coco.glob("*.yaml"):
        shutil.copy(f, out_coco / f.name)
    tum = "tum/rgbd_dataset_freiburg3_teddy"
    real = _frames(a.data / tum / "rgb", a.out / tum / "rgb", 100, 92)
    (a.out / tum / "rgb.txt").write_text("# timestamp filename (real frames only)\n" +
                                         "".join(f"{p.stem} rgb/{p.name}\n" for p in real))
    euroc = "euroc/V1_01_easy_micro/mav0/cam0/data"
    _frames(a.data / euroc, a.out / euroc, 48, 92)
    size = sum(p.stat().st_size for p in a.out.rglob("*") if p.is_file())
    print(f"{a.out}: {size / 2**20:.1f} MiB")


if __name__ == "__main__":
    main()
