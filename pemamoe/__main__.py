"""Command line: `python -m pemamoe <command>` (hand-written dispatcher; the work is in modules)."""

import argparse
import sys


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(prog="python -m pemamoe")
    sub = parser.add_subparsers(dest="command", required=True)
    fig = sub.add_parser("figures", help="execute every notebook and regenerate paper_figures/")
    fig.add_argument("--scale", default="small", help="ci | small | paper (default: small)")
    fig.add_argument("--figures-dir", default=None, help="output folder (default: paper_figures/)")
    fig.add_argument("--notebook", action="append", help="run only these notebooks (repeatable)")
    for name in ("export", "check-export"):
        sub.add_parser(name, help=f"literate {name.replace('-export', '')}")
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
        readme = make_figures(args.scale, args.figures_dir, args.notebook)
        print(f"[figures] provenance written to {readme}")
        return 0
    return 2


if __name__ == "__main__":
    sys.exit(main())
