"""Probe: multi-view steps at the pixels (and the cost) of one view (docs/equal_compute_log.md,
"Four views at the pixels of one"). Runs examples/train_3dgs.py with every step's views cut to
cells of their images before they render:

    # four views per step, each one cell of a 2 x 2 grid (a random permutation: the step covers
    # every part of the frame once); the stages in the 30k frame so that --steps rescales the clocks
    python benchmarks/probe_view_cells.py --cells grid -- --preset baseline --threshold-width 800 \
        --steps 3000 --stages 1:4:30000 --threads 1 --seed 0 --out out/cells4 [--views-scaling sqrt]
    # one view per step, one random quarter cell of it
    python benchmarks/probe_view_cells.py --cells one -- --preset baseline --threshold-width 800 \
        --steps 12000 --threads 1 --seed 0 --out out/cell1

A cell is a pinhole camera too: the same pose and focal lengths, the principal point moved by the
cell's corner, the cell's size; its target is the slice of the image (and of the mask). The
statistics and the threshold then see the cell's width, as a pyramid level's. Everything else is
train_3dgs.py's (its arguments after ``--``; its metrics.json and printout). Not an option of
the package: the probe found that it does not pay.
"""

from __future__ import annotations

import argparse
import runpy
import sys
from pathlib import Path
from typing import List, Tuple

import torch

from mvgs_plugin import schedule as schedule_module
from mvgs_plugin.camera import Camera

ROOT = Path(__file__).resolve().parents[1]
GRIDS = {1: (2, 2), 2: (2, 1), 4: (2, 2)}  # views per step -> cells across, down


def cell_camera(cam: Camera, x0: int, y0: int, width: int, height: int) -> Camera:
    """The camera of the image's pixels [x0, x0 + width) x [y0, y0 + height)."""
    K = cam.K.clone()
    K[0, 2] -= x0
    K[1, 2] -= y0
    return Camera(uid=cam.uid, name=cam.name, K=K, world_to_camera=cam.world_to_camera,
                  width=width, height=height, time=cam.time)


def cells_of(width: int, height: int, across: int, down: int) -> List[Tuple[int, int, int, int]]:
    """The grid's cells (x0, y0, w, h), row-major; the image's size must divide evenly, so that the
    cells of a step render in one call."""
    if width % across or height % down:
        raise ValueError(f"a {width}x{height} image does not split into {across}x{down} equal cells")
    w, h = width // across, height // down
    return [(i * w, j * h, w, h) for j in range(down) for i in range(across)]


def cut_to_cells(plan, generator: torch.Generator, mode: str):
    """The plan with its views cut to cells. "grid": M = 2 or 4 views get distinct cells of a grid
    of M cells (a random permutation); "one": one view gets one random cell of the 2 x 2 grid.
    Other plans are returned as they are."""
    m = len(plan.views)
    if (mode == "grid" and m not in (2, 4)) or (mode == "one" and m != 1):
        return plan
    W, H = plan.cameras[0].width, plan.cameras[0].height
    grid = cells_of(W, H, *GRIDS[m])
    if m == 1:  # column, then row
        col, row = (int(torch.randint(2, (1,), generator=generator)) for _ in range(2))
        order = [row * 2 + col]
    else:
        order = torch.randperm(len(grid), generator=generator).tolist()
    cams, images, masks = [], [], [] if plan.masks is not None else None
    for i, k in enumerate(order):
        x0, y0, w, h = grid[k]
        cams.append(cell_camera(plan.cameras[i], x0, y0, w, h))
        images.append(plan.images[i][y0:y0 + h, x0:x0 + w].contiguous())
        if masks is not None:
            masks.append(plan.masks[i][y0:y0 + h, x0:x0 + w].contiguous())
    plan.cameras, plan.images, plan.masks = cams, images, masks
    return plan


def main(argv=None) -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--cells", choices=("grid", "one"), required=True)
    ap.add_argument("--cell-seed", type=int, default=1234, help="seed of the cells' draw")
    ap.add_argument("train_args", nargs=argparse.REMAINDER, help="-- then examples/train_3dgs.py's arguments")
    args = ap.parse_args(argv)
    rest = args.train_args[1:] if args.train_args[:1] == ["--"] else args.train_args
    generator = torch.Generator().manual_seed(args.cell_seed)
    plain = schedule_module.ViewSchedule.next

    def next_in_cells(self):
        return cut_to_cells(plain(self), generator, args.cells)

    schedule_module.ViewSchedule.next = next_in_cells
    script = ROOT / "examples" / "train_3dgs.py"
    sys.argv = [str(script)] + rest
    try:
        runpy.run_path(str(script), run_name="__main__")
    finally:
        schedule_module.ViewSchedule.next = plain


if __name__ == "__main__":
    main()
