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

``fr1_xyz`` is the shared ``tum_fr1_xyz_head`` (all ten frames) with its stamps put back (:func:`retime_fr1_xyz`):
that folder carries approximate stamps (the first colour stamp + i/30 s) and one motion-capture row per frame,
each written at its frame's approximate stamp. The benchmark's own stamps are public facts of
``rgbd_dataset_freiburg1_xyz``: its first ten colour and depth stamps, and the stamps of the ten
motion-capture rows (the last row at or before each colour stamp, ten rows of the benchmark's ``groundtruth.txt``
whose values the shared file holds). The frame pairs are the shared folder's: colour image k with depth image k.
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

# rgbd_dataset_freiburg1_xyz (TUM RGB-D benchmark): its first ten colour stamps, first ten depth stamps, and the
# stamps of the ten motion-capture rows the shared tum_fr1_xyz_head holds (in its frame order)
FR1_XYZ_RGB_S = (1305031102.175304, 1305031102.211214, 1305031102.243211, 1305031102.275326, 1305031102.311267,
                 1305031102.343233, 1305031102.375329, 1305031102.411258, 1305031102.443271, 1305031102.475318)
FR1_XYZ_DEPTH_S = (1305031102.160407, 1305031102.194330, 1305031102.226738, 1305031102.262886, 1305031102.295279,
                   1305031102.329195, 1305031102.363013, 1305031102.394772, 1305031102.427815, 1305031102.462395)
FR1_XYZ_TRUTH_S = (1305031102.1658, 1305031102.2058, 1305031102.2359, 1305031102.2658, 1305031102.3058,
                   1305031102.3358, 1305031102.3659, 1305031102.4058, 1305031102.4359, 1305031102.4658)

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


def retime_fr1_xyz(source_root: Path, out_root: Path) -> int:
    """``fr1_xyz``: the shared ``tum_fr1_xyz_head`` with the benchmark's stamps; returns the bytes of images."""
    src = source_root / "tum_fr1_xyz_head"
    out = out_root / "fr1_xyz"
    rgb = read_tum_list(src / "rgb.txt")
    depth = read_tum_list(src / "depth.txt")
    truth = read_tum_list(src / "groundtruth.txt")
    n = len(FR1_XYZ_RGB_S)
    if not len(rgb) == len(depth) == len(truth) == n:
        raise SystemExit(f"{src}: expected {n} colour, depth and truth rows, got {len(rgb)}, {len(depth)}, "
                         f"{len(truth)}")
    if out.exists():
        shutil.rmtree(out)
    (out / "rgb").mkdir(parents=True)
    (out / "depth").mkdir()
    size = 0
    rgb_lines, depth_lines, pair_lines, truth_lines = [], [], [], []
    for k in range(n):
        names = []
        for (_, old), stamp, folder, lines in ((rgb[k], FR1_XYZ_RGB_S[k], "rgb", rgb_lines),
                                               (depth[k], FR1_XYZ_DEPTH_S[k], "depth", depth_lines)):
            name = f"{folder}/{stamp:.6f}.png"
            shutil.copyfile(src / old, out / name)
            size += (out / name).stat().st_size
            lines.append(f"{stamp:.6f} {name}")
            names.append(name)
        pair_lines.append(f"{FR1_XYZ_RGB_S[k]:.6f} {names[0]} {FR1_XYZ_DEPTH_S[k]:.6f} {names[1]}")
        truth_lines.append(f"{FR1_XYZ_TRUTH_S[k]:.4f} {truth[k][1]}")
    sequence = "rgbd_dataset_freiburg1_xyz"
    for file, what, columns, lines in (("rgb.txt", "colour images", "timestamp filename", rgb_lines),
                                       ("depth.txt", "depth maps", "timestamp filename", depth_lines),
                                       ("associations.txt", "colour/depth pairs",
                                        "rgb_timestamp rgb_filename depth_timestamp depth_filename", pair_lines),
                                       ("groundtruth.txt", "ground truth trajectory", "timestamp tx ty tz qx qy qz qw",
                                        truth_lines)):
        (out / file).write_text(HEADER.format(what=what, sequence=sequence) + f"# {columns}\n"
                                + "\n".join(lines) + "\n", encoding="utf-8")
    shutil.copyfile(src / "camera.yaml", out / "camera.yaml")
    first, last = FR1_XYZ_RGB_S[0], FR1_XYZ_RGB_S[-1]
    (out / "README.md").write_text(f"""# fr1_xyz: {n} real RGB-D frames with motion-capture truth, at their own stamps

The first {n} colour and depth frames ({first:.6f} to {last:.6f}, {last - first:.2f} s) of the TUM RGB-D
benchmark sequence `{sequence}` (J. Sturm, N. Engelhard, F. Endres, W. Burgard, D. Cremers: "A Benchmark for
the Evaluation of RGB-D SLAM Systems", IROS 2012; Computer Vision Group, TU Munich,
https://cvg.cit.tum.de/data/datasets/rgbd-dataset), licensed under CC BY 4.0
(https://creativecommons.org/licenses/by/4.0/): see LICENSE in the folder above.

Why this clip: the shared `tum_fr1_xyz_head` (the same images) carries approximate stamps (the first colour
stamp + i/30 s) and writes each of its ten motion-capture rows at its frame's approximate stamp. The real colour
frames are 32-36 ms apart and the rows were taken on the 100 Hz grid (the last row at or before each colour
stamp, 5-10 ms before it): the rows are 30 or 40 ms apart where the frames are 32 or 36 ms apart, an error of up to
4 ms (1.5 mm at the clip's 0.37 m/s) in the truth of a frame-to-frame motion, the same for every method.

How it was made: `scripts/make_tum_fixture.py` from the shared folder `tum_fr1_xyz_head` (whose images and rows
come from the public repository pfontana96/dense-visual-odometry, `tests/test_data`; its
`filtered_best10_gt.json` lists the ten rows with their stamps). The PNG files are the shared folder's images byte
for byte, renamed to the benchmark's stamps (`rgb/`, `depth/`: 16-bit, 5000 = 1 m, 0 = missing);
`rgb.txt` and `depth.txt` give the benchmark's first {n} colour and depth stamps; `associations.txt` pairs colour
image k with depth image k, as the shared folder does (each depth image 12-17 ms before its colour image; TUM's
nearest-stamp rule would pair two of them differently and drop a colour frame); `groundtruth.txt` holds the ten
motion-capture rows with the benchmark's stamps for them; the truth at a colour stamp is interpolated between
rows 30-40 ms apart (the last frame, after the last row, has none). `camera.yaml` holds TUM's recommended
intrinsics for the registered depth and the depth scale.
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
    n = retime_fr1_xyz(args.source, args.out)
    total += n
    print(f"{args.out / 'fr1_xyz'}: {len(FR1_XYZ_RGB_S)} frames, {n / 1e6:.1f} MB of images")
    print(f"total {total / 1e6:.1f} MB")


if __name__ == "__main__":
    main()
