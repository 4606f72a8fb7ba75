"""Command line: `python -m pemamoe <command>` (hand-written dispatcher; the work is in modules)."""

import argparse
import sys
from pathlib import Path


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(prog="python -m pemamoe")
    sub = parser.add_subparsers(dest="command", required=True)
    fig = sub.add_parser("figures", help="execute every notebook and regenerate paper_figures/")
    fig.add_argument("--scale", default="small", help="ci | small | paper (default: small)")
    fig.add_argument("--figures-dir", default=None, help="output folder (default: paper_figures/)")
    fig.add_argument("--notebook", action="append", help="run only these notebooks (repeatable)")
    fig.add_argument("--backend", default="local", help="sweep backend: local | ray")
    fig.add_argument("--workers", type=int, default=2, help="parallel training runs")
    fig.add_argument("--ray-address", default=None, help="Ray cluster address (backend ray)")
    sweep = sub.add_parser("sweep", help="run experiment sweeps (see notebook 09)", add_help=False)
    for name in ("export", "check-export"):
        sub.add_parser(name, help=f"literate {name.replace('-export', '')}")
    argv = sys.argv[1:] if argv is None else list(argv)
    if argv[:1] == ["sweep"]:  # the sweep command owns its own options
        from pemamoe.sweep import sweep_cli

        return sweep_cli(argv[1:])
    args = parser.parse_args(argv)

    if args.command in ("export", "check-export"):
        from pemamoe import literate

        return literate.main(["export" if args.command == "export" else "check"])
    if args.command == "figures":
        from pemamoe.core import check_scale, make_figures

        try:
            check_scale(args.scale)
        except ValueError as err:
            parser.error(str(err))
        # A relative --figures-dir is relative to where the command runs (make_figures alone would
        # read it under the repository root, as the notebooks do).
        figures_dir = Path(args.figures_dir).resolve() if args.figures_dir else None
        readme = make_figures(args.scale, figures_dir, args.notebook, backend=args.backend,
                              workers=args.workers, ray_address=args.ray_address)
        print(f"[figures] provenance written to {readme}")
        return 0
    return 2


if __name__ == "__main__":
    sys.exit(main())
