"""``usdfiber plugin-path``: where usdfiber's USD plugins live.

For programs that open stages before they could import usdfiber (usdview, a DCC):
``export PXR_PLUGINPATH_NAME=$(usdfiber plugin-path)``.
"""
from __future__ import annotations

import argparse
import os


def register(sub: argparse._SubParsersAction) -> None:
    from usdfiber.cli import one_line_errors

    p = sub.add_parser(
        "plugin-path",
        help="print the plugin directories to put on PXR_PLUGINPATH_NAME",
        description=__doc__,
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    p.set_defaults(func=run)
    one_line_errors(p)


def run(args: argparse.Namespace) -> int:
    from usdfiber import plugin_paths

    print(os.pathsep.join(str(p) for p in plugin_paths()))
    return 0
