"""Peak memory of merging per-channel volume series into one ``(T, C, Z, Y, X)`` image.

Three channel series of ``T`` volumes are written as OME-TIFF, then merged in a fresh process
each way: stacked in memory and written as one OME-TIFF (the merge before OME-Zarr), and
streamed into an OME-Zarr image one time point at a time (:func:`fgat.app.pipeline.merge_channels`,
what ``fgat pipeline --channels all`` does). Reported for two series lengths: the peak of the
memory Python and NumPy allocate during the merge (``tracemalloc``, after a merge of one-voxel
series has made the imports), in frames of one channel's volume, and the process's peak
resident set (``ru_maxrss``, imports and the codecs' buffers included); the streamed merge
should not grow with ``T``. Extrapolation to Fig. 5's 166 x
3 x 151 x 384 x 384 (44 GB stacked) is the stacked peak per frame times 166 x 3 frames.

    python benchmarks/merge_memory.py [--quick] [--out benchmarks/results/merge_memory.json]
"""

from __future__ import annotations

import multiprocessing
import resource
import tempfile
import tracemalloc
from pathlib import Path

import numpy as np

from fgat.app.pipeline import merge_channels
from fgat.app.recipes.benchmark import parser, write_json
from fgat.io.images import read_series, write_tiff

CHANNELS = 3
FIG5 = {"frames": 166, "channels": 3, "shape": (151, 384, 384)}


def merge(way: str, series: list[str], out: str) -> tuple[float, float]:
    """Merge ``series`` ``way`` ("stacked" or "streamed") in this process, after a merge of
    one-voxel series has made the imports: the peak of the memory Python and NumPy allocate
    during the merge (``tracemalloc``) and the peak resident set (``ru_maxrss``), bytes."""
    folder = Path(tempfile.mkdtemp(dir=Path(out).parent))
    tiny = [write_tiff(folder / f"{c}.ome.tif", np.zeros((2, 1, 1, 1), np.float32)) for c in "ab"]
    run(way, [str(path) for path in tiny], str(folder / f"warm{Path(out).suffix}"))
    tracemalloc.start()
    run(way, series, out)
    _, allocated = tracemalloc.get_traced_memory()
    tracemalloc.stop()
    return float(allocated), float(resource.getrusage(resource.RUSAGE_SELF).ru_maxrss * 1024)


def run(way: str, series: list[str], out: str) -> None:
    if way == "stacked":
        volumes = np.stack([read_series(path) for path in series], axis=1)
        write_tiff(out, volumes, axes="TCZYX")
    else:
        merge_channels([Path(path) for path in series], Path(out))


def main() -> None:
    args = parser(__doc__, "benchmarks/results/merge_memory.json", "smaller volumes").parse_args()
    shape = (16, 96, 96) if args.quick else (32, 192, 192)
    frame_bytes = int(np.prod(shape)) * 4
    context = multiprocessing.get_context("spawn")
    rows = []
    with tempfile.TemporaryDirectory() as folder:
        for frames in (8, 32):
            rng = np.random.default_rng(0)
            series = []
            for channel in range(CHANNELS):
                path = Path(folder) / f"ch{channel}_{frames}.ome.tif"
                volumes = rng.random((frames, *shape), dtype=np.float32)
                write_tiff(path, volumes, axes="TZYX", voxel_size_um=(1.5, 0.975, 0.975))
                series.append(str(path))
            for way, suffix in (("stacked", ".ome.tif"), ("streamed", ".ome.zarr")):
                out = str(Path(folder) / f"merged_{way}_{frames}{suffix}")
                with context.Pool(1) as pool:
                    allocated, resident = pool.apply(merge, (way, series, out))
                rows.append(
                    {
                        "way": way,
                        "frames": frames,
                        "channels": CHANNELS,
                        "volume": list(shape),
                        "peak_gb": allocated / 1e9,
                        "peak_frames": allocated / frame_bytes,
                        "max_rss_gb": resident / 1e9,
                    }
                )
    print(
        f"{'merge':>9} {'T':>4} {'C':>3} {'volume':>14} {'peak (GB)':>10} {'in frames':>10} "
        f"{'max RSS (GB)':>13}"
    )
    for row in rows:
        print(
            f"{row['way']:>9} {row['frames']:>4} {row['channels']:>3} "
            f"{'x'.join(map(str, row['volume'])):>14} {row['peak_gb']:>10.3f} "
            f"{row['peak_frames']:>10.1f} {row['max_rss_gb']:>13.3f}"
        )
    fig5_frame = int(np.prod(FIG5["shape"])) * 4
    streamed = max(row["peak_frames"] for row in rows if row["way"] == "streamed")
    print(
        f"\nFig. 5 ({FIG5['frames']} x {FIG5['channels']} x {FIG5['shape']}): stacked about "
        f"{FIG5['frames'] * FIG5['channels'] * fig5_frame / 1e9:.0f} GB and up; streamed about "
        f"{streamed * fig5_frame / 1e9:.2f} GB ({streamed:.1f} frames of {fig5_frame / 1e6:.0f} MB)"
    )
    write_json(args.out, {"rows": rows, "fig5_streamed_gb": streamed * fig5_frame / 1e9})


if __name__ == "__main__":
    main()
