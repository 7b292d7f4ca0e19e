"""``magcal batch``: correct (or calibrate and correct) a campaign's recordings on Dask, with a campaign
report. The command lives in :mod:`magcal_ros.app.batch` (planning, tasks and report beside it); this
module adds its parser like every other command's."""

from __future__ import annotations

import argparse

from magcal_ros.app.commands.common import _subcommand


def add_parser(sub: argparse._SubParsersAction) -> None:  # type: ignore[type-arg]
    """Add ``magcal batch`` to the subcommands ``sub`` (Dask itself is imported only when a batch runs)."""
    from magcal_ros.app.batch import add_batch_parser

    add_batch_parser(sub, _subcommand)
