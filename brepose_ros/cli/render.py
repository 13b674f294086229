"""brepose-render: render a synthetic scene folder of a part with exact ground truth.

    brepose-render MODEL.step|builtin:NAME OUTDIR --n N --seed S [--occlusion F]
                   [--clutter N] [--noise SIGMA] [--offcenter] [--width W --height H --fx F]
                   [--span-min A --span-max B] [--elevation LO HI] [--color] [--look plain|varied]

OUTDIR gets camera.json, model.step, images/, masks/ and gt.json (../shared/CONVENTIONS.md).
A bad input prints the reason on stderr and exits with status 2.
"""
from __future__ import annotations

import argparse
import tempfile
import time
from pathlib import Path

import numpy as np

from ..synthetic import shapes
from ..synthetic.scenes import LOOKS, SceneConfig, generate_scene
from .common import ArgumentParser, non_negative_float, non_negative_int, positive_float, positive_int, run

BUILTIN_PREFIX = "builtin:"


EXAMPLE = """examples:
  brepose-render my_part.step renders --n 8 --seed 0                              # centred, clean
  brepose-render builtin:sharp_bracket cluttered --n 8 --clutter 3 --offcenter --noise 4"""


def parser() -> argparse.ArgumentParser:
    d = SceneConfig()
    p = ArgumentParser(prog="brepose-render", description=__doc__.splitlines()[0], epilog=EXAMPLE)
    p.add_argument("model", help=f"STEP file, or {BUILTIN_PREFIX}NAME of a built-in part "
                                 f"({', '.join(shapes.BUILTIN)})")
    p.add_argument("outdir", type=Path, help="new (or empty) scene folder")
    p.add_argument("--n", type=positive_int, default=10, help="number of images (default 10)")
    p.add_argument("--seed", type=non_negative_int, default=0, help="random seed; image i depends on (seed, i) only")
    p.add_argument("--occlusion", type=non_negative_float, default=d.occlusion,
                   help="share of the part to hide behind an occluder, 0-0.5 (default 0)")
    p.add_argument("--clutter", type=non_negative_int, default=d.clutter, help="shapes behind the part (default 0)")
    p.add_argument("--noise", type=non_negative_float, default=d.noise,
                   help=f"noise sigma, grey levels (default {d.noise})")
    p.add_argument("--blur", type=non_negative_float, default=d.blur, help=f"blur sigma, pixels (default {d.blur})")
    p.add_argument("--offcenter", action="store_true", help="part anywhere in the central 80 %% of the image")
    p.add_argument("--width", type=positive_int, default=d.width)
    p.add_argument("--height", type=positive_int, default=d.height)
    p.add_argument("--fx", type=positive_float, default=d.fx, help=f"focal length in pixels, fx = fy (default {d.fx})")
    p.add_argument("--span-min", type=positive_float, default=d.span[0],
                   help=f"smallest part size, share of the image's smaller side (default {d.span[0]})")
    p.add_argument("--span-max", type=positive_float, default=d.span[1],
                   help=f"largest part size (default {d.span[1]})")
    p.add_argument("--elevation", type=float, nargs=2, metavar=("LO", "HI"),
                   help="viewpoints only this many degrees above the model XY plane (default: whole sphere)")
    p.add_argument("--color", action="store_true", help="BGR images instead of grey")
    p.add_argument("--look", choices=LOOKS, default=d.look,
                   help="plain: fixed lights and bench; varied: random lights, gloss, backgrounds, blur, "
                        f"noise and props per image (default {d.look})")
    p.add_argument("-q", "--quiet", action="store_true", help="no progress bar")
    return p


def model_step(model: str, folder: Path) -> Path:
    """The STEP file of ``model``: a path as given, or a built-in part exported into ``folder``."""
    if not model.startswith(BUILTIN_PREFIX):
        return Path(model)
    name = model[len(BUILTIN_PREFIX):]
    if name not in shapes.BUILTIN:
        raise ValueError(f"unknown built-in part {name!r}; choose from {', '.join(shapes.BUILTIN)}")
    return shapes.export_step(name, folder / f"{name}.step")


def main(argv: list[str] | None = None) -> int:
    args = parser().parse_args(argv)

    def render_scene() -> None:
        config = SceneConfig(width=args.width, height=args.height, fx=args.fx,
                             span=(args.span_min, args.span_max),
                             elevation=tuple(args.elevation) if args.elevation else None,
                             offcenter=args.offcenter, occlusion=args.occlusion, clutter=args.clutter,
                             noise=args.noise, blur=args.blur, color=args.color, look=args.look)
        started = time.perf_counter()
        with tempfile.TemporaryDirectory() as tmp:
            step = model_step(args.model, Path(tmp))
            scene = generate_scene(step, args.outdir, args.n, args.seed, config, progress=not args.quiet)
        occlusion = np.mean([e.occlusion for e in scene.entries])
        print(f"{scene.folder}: {len(scene.entries)} images, mean occlusion {occlusion:.3f}, "
              f"{time.perf_counter() - started:.1f} s")

    return run(render_scene)


if __name__ == "__main__":
    raise SystemExit(main())
