"""Reading a flight recording (an MCAP file of runtime.process.recorder): its SafeMove
metadata and its messages in the order they were written. `safemove replay` and
`safemove plot` read recordings through this one function.

The file is read as a stream, record after record, not through its index: a recording cut
short (the recorder stopped at a full disk, the robot lost power) has no index or footer, and
everything before the cut is still read.
"""

from __future__ import annotations

import struct
from collections.abc import Iterator
from pathlib import Path
from typing import Any

from runtime.errors import UserError

_BROKEN = (ValueError, EOFError, struct.error)  # what a cut or a corrupt record raises


def _records(path: Path) -> Iterator[Any]:
    """The file's records as a stream; it ends where the file stops making sense."""
    from mcap.exceptions import McapError
    from mcap.stream_reader import StreamReader

    try:
        f = path.open("rb")
    except OSError as exc:
        raise UserError(f"{path}: cannot open: {exc.strerror or exc}") from None
    with f:
        try:
            yield from StreamReader(f).records
        except (McapError, *_BROKEN):
            return


def read_flight_log(path: Path) -> tuple[dict[str, str], Iterator[tuple[str, bytes]]]:
    """The recording's metadata and its messages (topic, data) in the order they were written.
    A file that cannot be opened, is not an MCAP file or has no 'safemove' metadata is a
    UserError; a file cut short yields what is whole."""
    from mcap.exceptions import McapError
    from mcap.records import Metadata
    from mcap.stream_reader import StreamReader

    try:
        with path.open("rb") as f:
            StreamReader(f).records.__next__()  # the header: is it an MCAP file at all?
    except OSError as exc:
        raise UserError(f"{path}: cannot open: {exc.strerror or exc}") from None
    except (McapError, StopIteration, *_BROKEN) as exc:
        raise UserError(f"{path}: not a readable MCAP file ({exc or type(exc).__name__})"
                        ) from None
    metadata = next((r.metadata for r in _records(path)
                     if isinstance(r, Metadata) and r.name == "safemove"), None)
    if metadata is None:
        raise UserError(f"{path}: not a SafeMove flight recording (no 'safemove' metadata)")

    def messages() -> Iterator[tuple[str, bytes]]:
        from mcap.records import Channel, Message

        topics: dict[int, str] = {}
        for record in _records(path):
            if isinstance(record, Channel):
                topics[record.id] = record.topic
            elif isinstance(record, Message):
                yield topics[record.channel_id], record.data

    return dict(metadata), messages()
