"""Reading an se3sync MCAP log back (`read_log`), JSON or ROS 2 CDR messages alike."""
from __future__ import annotations

import json

from mcap.records import Attachment, Channel, Message, Metadata, Schema
from mcap.stream_reader import StreamReader

from controller.errors import Se3SyncError

from . import cdr

__all__ = ["read_log"]


def read_log(path, topics=None) -> dict:
    """Reads an se3sync MCAP back: {"metadata": {...}, "attachments": {name: bytes},
    "messages": {topic: [(log_time_ns, decoded JSON), ...]}, "truncated": bool, "outcome":
    {steps, interrupted, diverged, ...} or None (`McapLogger.outcome`)}. A CDR message
    is decoded to the dict its JSON message would give (`cdr.decode`). ``topics``: decode the
    messages of these topics only (the scene and 1000 trails of a large log are most of it).

    One streaming pass (mcap's StreamReader), so a file without a summary section, or with a
    torn tail (a killed run), yields every record before the tear. Raises Se3SyncError (one
    line) when the file is unreadable or is not an se3sync log.
    """
    out = {"metadata": None, "attachments": {}, "messages": {}, "truncated": False,
           "outcome": None}
    channels, schemas = {}, {}
    n_records = 0
    try:
        f = open(path, "rb")
    except FileNotFoundError:
        raise Se3SyncError(f"{path}: no such file") from None
    except OSError as exc:
        raise Se3SyncError(f"{path}: cannot read: {exc.strerror or exc}") from None
    with f:
        try:
            for rec in StreamReader(f, skip_magic=False).records:
                n_records += 1
                if isinstance(rec, Message):
                    ch = channels.get(rec.channel_id)
                    if ch is not None:
                        topic, ros2 = ch
                        out["messages"].setdefault(topic, []).append(
                            (rec.log_time, json.loads(rec.data) if ros2 is None
                             else cdr.decode(ros2, rec.data)))
                elif isinstance(rec, Schema):
                    schemas[rec.id] = rec
                elif isinstance(rec, Channel):
                    sch = schemas.get(rec.schema_id)
                    if rec.message_encoding == "json":
                        channels[rec.id] = (rec.topic, None)
                    elif (rec.message_encoding == "cdr" and sch is not None
                          and sch.encoding == "ros2msg" and sch.name in cdr.SCHEMA.values()):
                        channels[rec.id] = (rec.topic, sch.name)
                    if topics is not None and rec.topic not in topics:
                        channels.pop(rec.id, None)
                elif isinstance(rec, Metadata):
                    if rec.name == "se3sync":
                        out["metadata"] = dict(rec.metadata)
                    elif rec.name == "se3sync.outcome":
                        out["outcome"] = {k: json.loads(v) for k, v in rec.metadata.items()}
                elif isinstance(rec, Attachment):
                    out["attachments"][rec.name] = bytes(rec.data)
        except Exception as exc:  # mcap raises assorted errors on garbage or torn input
            if n_records == 0 or out["metadata"] is None:
                raise Se3SyncError(f"{path}: not a readable MCAP file ({type(exc).__name__}: "
                                   f"{' '.join(str(exc).split())[:160]})") from None
            out["truncated"] = True
    if out["metadata"] is None:
        raise Se3SyncError(f"{path}: not an se3sync log (no 'se3sync' metadata record)")
    return out
