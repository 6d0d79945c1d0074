"""Reads back the scalars of a TensorBoard event file (``events.out.tfevents.*``) that tensorboardX wrote: the
tests check the logged scalars with it. The file is a TFRecord stream (a u64 length, its masked CRC, the data, its
masked CRC) of ``Event`` protos."""

import struct


def scalars(path) -> dict:
    """{(tag, step): value} of every scalar in the file."""
    from tensorboardX.proto.event_pb2 import Event

    out = {}
    with open(path, "rb") as f:
        buf = f.read()
    pos = 0
    while pos + 12 <= len(buf):
        (length,) = struct.unpack("<Q", buf[pos:pos + 8])
        data = buf[pos + 12:pos + 12 + length]
        pos += 12 + length + 4
        event = Event()
        event.ParseFromString(data)
        for value in event.summary.value:
            out[(value.tag, event.step)] = value.simple_value
    return out
