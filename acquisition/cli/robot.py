"""`cdpr robot show [NAME]`: print a robot description (YAML)."""

from __future__ import annotations

import sys

from calib.robot import builtin_robot_names, builtin_robot_yaml


def register(sub) -> None:
    parser = sub.add_parser("robot", help="robot descriptions")
    rsub = parser.add_subparsers(dest="robot_command", metavar="ACTION")
    show = rsub.add_parser("show", help="print the YAML description of a built-in robot")
    show.add_argument("name", nargs="?", default="irma4u", help=f"one of: {', '.join(builtin_robot_names())}")
    show.set_defaults(func=_show)
    lst = rsub.add_parser("list", help="list the built-in robots")
    lst.set_defaults(func=lambda args: print("\n".join(builtin_robot_names())) or 0)


def _show(args) -> int:
    sys.stdout.write(builtin_robot_yaml(args.name))
    return 0
