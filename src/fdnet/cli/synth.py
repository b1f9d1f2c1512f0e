"""`fdnet synth`: write the SYNTHETIC multi-condition route (a demo and test dataset, rendered)."""

from __future__ import annotations


def register(sub) -> None:
    p = sub.add_parser(
        "synth",
        help="render the synthetic multi-condition route (summer/autumn/winter/night) to a folder",
        description="Render a SYNTHETIC route (not photographs): the same street seen in several "
        "conditions, frame i = the same place in each. Writes OUT/<condition>/frame_NNNNN.png "
        "and OUT/README.txt. Ground truth is frame-aligned; use a tolerance of 1 frame.",
    )
    p.add_argument("--out", required=True, help="output folder (new, empty, or a synthetic route written before)")
    p.add_argument("--num-frames", type=int, default=300, help="frames per condition (default 300)")
    p.add_argument(
        "--conditions",
        default="summer,autumn,winter,night",
        help="comma-separated, from summer,autumn,winter,night (default all four)",
    )
    p.add_argument("--seed", type=int, default=0, help="scene and nuisance seed (default 0)")
    p.add_argument("--size", default="64x128", help="frame size HxW in pixels (default 64x128)")
    p.add_argument(
        "--step", type=float, default=0.5, help="camera movement between frames, in frame heights (default 0.5)"
    )
    p.set_defaults(func=run)


def parse_size(text: str) -> tuple[int, int]:
    from fdnet.errors import ConfigError

    try:
        h, w = (int(v) for v in text.lower().split("x"))
    except ValueError as exc:
        raise ConfigError(f"--size {text!r}: expected HxW, e.g. 64x128") from exc
    return h, w


def run(args) -> int:
    import time

    from fdnet.data.synthetic import generate_route

    conditions = [c.strip() for c in args.conditions.split(",") if c.strip()]
    t0 = time.perf_counter()
    dataset = generate_route(
        args.out,
        frames=args.num_frames,
        conditions=conditions,
        seed=args.seed,
        size=parse_size(args.size),
        step=args.step,
    )
    counts = ", ".join(f"{name} {len(t)}" for name, t in dataset.traverses.items())
    print(f"wrote SYNTHETIC route to {dataset.root} ({counts} frames) in {time.perf_counter() - t0:.1f} s")
    return 0
