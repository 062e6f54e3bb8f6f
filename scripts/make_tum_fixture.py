#!/usr/bin/env python3
"""Cut the small real-data test fixture ``tests/data/tum/<name>/`` out of the shared TUM sequences.

Run from the repository root: ``python scripts/make_tum_fixture.py [--source ../shared/data] [--out tests/data/tum]``.

For each clip below it takes ``frames`` consecutive *associated* colour/depth pairs (TUM's ``associate.py`` rule,
the one :class:`quadlink.datasets.tum.TumSequence` applies: nearest stamps, at most 20 ms apart) starting at the
associated pair ``start`` of the source folder, and writes, in TUM's layout:

* ``rgb/`` and ``depth/``: the original PNG files, copied byte for byte (16-bit depth stays exact);
* ``rgb.txt`` and ``depth.txt``: the stamps and file names of exactly those images (a colour frame the sensor
  delivered without a depth image is left out; the stamps keep the gap it leaves);
* ``groundtruth.txt``: the source's 100 Hz motion-capture rows from 0.1 s before the first to 0.1 s after the last
  colour stamp (enough samples around every frame to interpolate the truth at its stamp);
* ``camera.yaml``: the source's intrinsics and depth scale, unchanged;
* ``README.md``: where the clip comes from (TUM RGB-D benchmark, Sturm et al. 2012, CC BY 4.0) and how it was cut.

The clips are chosen for what the tests need: ``fr1_rpy`` holds the fastest hand-held rotation of the shared
``tum_fr1_rpy_mid`` (up to 7 degrees between frames, with dropped frames), ``fr3_teddy`` a slower translation with
motion-capture truth at every frame. PNG frames weigh 0.55-0.63 MB each, so each clip is kept to ten frames.
"""

from __future__ import annotations

import argparse
import shutil
import sys
from dataclasses import dataclass
from pathlib import Path

REPO = Path(__file__).resolve().parent.parent
sys.path.insert(0, str(REPO))

from quadlink.datasets.tum import associate, read_tum_list  # noqa: E402


@dataclass(frozen=True)
class Clip:
    name: str          # folder under tests/data/tum
    source: str        # folder under the shared data
    sequence: str      # the TUM benchmark's name of the sequence
    start: int         # first associated colour/depth pair of the source folder
    frames: int        # consecutive associated pairs
    why: str


CLIPS = (
    Clip("fr1_rpy", "tum_fr1_rpy_mid", "rgbd_dataset_freiburg1_rpy", 30, 10,
         "the fastest hand-held roll/pitch/yaw of the shared tum_fr1_rpy_mid (3-7 degrees between frames, "
         "several colour frames dropped by the sensor): the odometry's hardest case"),
    Clip("fr3_teddy", "tum_fr3_teddy_head", "rgbd_dataset_freiburg3_teddy", 5, 10,
         "a slow hand-held pass (about 15 mm and 1 degree between frames) around a teddy bear, with motion-capture "
         "truth at every frame (the shared tum_fr3_teddy_head's first five frames have none)"),
)

GT_MARGIN_S = 0.1
HEADER = "# {what} of {sequence} (TUM RGB-D benchmark, CC BY 4.0), cut by scripts/make_tum_fixture.py\n"


def cut(clip: Clip, source_root: Path, out_root: Path) -> int:
    """Write one clip; returns the bytes of images copied."""
    src = source_root / clip.source
    out = out_root / clip.name
    rgb = read_tum_list(src / "rgb.txt")
    depth = read_tum_list(src / "depth.txt")
    pairs = associate([s for s, _ in rgb], [s for s, _ in depth])[clip.start:clip.start + clip.frames]
    if len(pairs) != clip.frames:
        raise SystemExit(f"{src}: only {len(pairs)} associated frames from pair {clip.start}")
    if out.exists():
        shutil.rmtree(out)
    (out / "rgb").mkdir(parents=True)
    (out / "depth").mkdir()
    size = 0
    rgb_lines, depth_lines = [], []
    for i, j in pairs:
        for (stamp, name), lines in ((rgb[i], rgb_lines), (depth[j], depth_lines)):
            shutil.copyfile(src / name, out / name)
            size += (out / name).stat().st_size
            lines.append(f"{stamp:.6f} {name}")
    (out / "rgb.txt").write_text(HEADER.format(what="colour images", sequence=clip.sequence)
                                 + "# timestamp filename\n" + "\n".join(rgb_lines) + "\n", encoding="utf-8")
    (out / "depth.txt").write_text(HEADER.format(what="depth maps", sequence=clip.sequence)
                                   + "# timestamp filename\n" + "\n".join(depth_lines) + "\n", encoding="utf-8")
    t0, t1 = rgb[pairs[0][0]][0] - GT_MARGIN_S, rgb[pairs[-1][0]][0] + GT_MARGIN_S
    gt_lines = [line for line in (src / "groundtruth.txt").read_text(encoding="utf-8").splitlines()
                if line.strip() and not line.startswith("#") and t0 <= float(line.split()[0]) <= t1]
    (out / "groundtruth.txt").write_text(HEADER.format(what="ground truth trajectory", sequence=clip.sequence)
                                         + "# timestamp tx ty tz qx qy qz qw\n" + "\n".join(gt_lines) + "\n",
                                         encoding="utf-8")
    shutil.copyfile(src / "camera.yaml", out / "camera.yaml")
    first, last = rgb[pairs[0][0]][0], rgb[pairs[-1][0]][0]
    (out / "README.md").write_text(f"""# {clip.name}: {clip.frames} real RGB-D frames with motion-capture ground truth

{clip.frames} consecutive associated colour/depth frames ({first:.6f} to {last:.6f}, {last - first:.2f} s) of the
TUM RGB-D benchmark sequence `{clip.sequence}` (J. Sturm, N. Engelhard, F. Endres, W. Burgard, D. Cremers: "A
Benchmark for the Evaluation of RGB-D SLAM Systems", IROS 2012; Computer Vision Group, TU Munich,
https://cvg.cit.tum.de/data/datasets/rgbd-dataset), licensed under CC BY 4.0
(https://creativecommons.org/licenses/by/4.0/): see LICENSE in the folder above.

Why this clip: {clip.why}.

How it was cut: `scripts/make_tum_fixture.py` from the shared folder `{clip.source}` (associated pairs
{clip.start} to {clip.start + clip.frames - 1}, TUM's association rule: nearest stamps, at most 20 ms apart). The
PNG files are the benchmark's, byte for byte (`depth/`: 16-bit, 5000 = 1 m, 0 = missing); `rgb.txt` and
`depth.txt` list exactly these images with the sequence's own stamps (a colour frame without depth is left out,
its gap stays in the stamps); `groundtruth.txt` holds the benchmark's 100 Hz motion-capture rows from
{GT_MARGIN_S} s before the first to {GT_MARGIN_S} s after the last colour stamp; `camera.yaml` holds TUM's
recommended intrinsics for the registered depth and the depth scale.
""", encoding="utf-8")
    return size


LICENSE = """The folders below this one hold short clips of the TUM RGB-D benchmark
(https://cvg.cit.tum.de/data/datasets/rgbd-dataset), Computer Vision Group, Technical University of Munich:

  J. Sturm, N. Engelhard, F. Endres, W. Burgard, D. Cremers. A Benchmark for the Evaluation of RGB-D SLAM
  Systems. Proc. of the International Conference on Intelligent Robot Systems (IROS), 2012.

The data set is licensed under the Creative Commons Attribution 4.0 International License (CC BY 4.0):
https://creativecommons.org/licenses/by/4.0/. The images are unchanged; the clips (frame ranges, list files,
ground-truth rows) were cut by scripts/make_tum_fixture.py, as each folder's README.md describes.
"""


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--source", type=Path, default=REPO.parent / "shared" / "data")
    ap.add_argument("--out", type=Path, default=REPO / "tests" / "data" / "tum")
    args = ap.parse_args()
    args.out.mkdir(parents=True, exist_ok=True)
    (args.out / "LICENSE").write_text(LICENSE, encoding="utf-8")
    total = 0
    for clip in CLIPS:
        n = cut(clip, args.source, args.out)
        total += n
        print(f"{args.out / clip.name}: {clip.frames} frames, {n / 1e6:.1f} MB of images")
    print(f"total {total / 1e6:.1f} MB")


if __name__ == "__main__":
    main()
