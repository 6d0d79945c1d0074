"""Reads back what an offline Weights & Biases run wrote (``run-<id>.wandb``), without wandb's service or a
network: the tests check the logged scalars with it.

The file is wandb's variant of the LevelDB log format: a 7-byte header (``:W&B``, magic 0xBEE1, version 0), then
32 KiB blocks of chunks, each a CRC-32 of its type byte and data, a length, a type (1 full, 2 first, 3 middle,
4 last) and the data; fewer than 7 bytes left in a block are padding. Each record is a serialised
``wandb.proto.wandb_internal_pb2.Record``.
"""

import json
import struct
import zlib

HEADER, BLOCK, CHUNK_HEADER = 7, 32768, 7


def records(path):
    """The serialised records (bytes) of a ``.wandb`` file, in order."""
    with open(path, "rb") as f:
        buf = f.read()
    ident, magic, version = struct.unpack("<4sHB", buf[:HEADER])
    if (ident, magic, version) != (b":W&B", 0xBEE1, 0):
        raise ValueError(f"{path}: not a W&B run file")
    pos, pending = HEADER, b""
    while pos + CHUNK_HEADER <= len(buf):
        left = BLOCK - pos % BLOCK
        if left < CHUNK_HEADER:
            pos += left
            continue
        crc, length, kind = struct.unpack("<IHB", buf[pos:pos + CHUNK_HEADER])
        if crc == 0 and length == 0 and kind == 0:
            pos += left
            continue
        data = buf[pos + CHUNK_HEADER:pos + CHUNK_HEADER + length]
        if len(data) < length:
            break
        if zlib.crc32(data, zlib.crc32(bytes([kind]))) & 0xFFFFFFFF != crc:
            raise ValueError(f"{path}: bad checksum at offset {pos}")
        pos += CHUNK_HEADER + length
        if kind == 1:
            yield data
        elif kind == 2:
            pending = data
        elif kind == 3:
            pending += data
        elif kind == 4:
            yield pending + data
            pending = b""


def history(path) -> list[dict]:
    """Every ``run.log`` row of the file, in order: {key: value} (wandb's own keys, ``_step`` …, left out)."""
    from wandb.proto import wandb_internal_pb2 as pb

    rows = []
    for data in records(path):
        rec = pb.Record()
        rec.ParseFromString(data)
        if rec.WhichOneof("record_type") == "history":
            row = {}
            for item in rec.history.item:
                key = item.key or "/".join(item.nested_key)
                if not key.startswith("_"):
                    row[key] = json.loads(item.value_json)
            rows.append(row)
    return rows


def step_metrics(path) -> dict:
    """{metric or glob: its step metric} of the file's ``define_metric`` records."""
    from wandb.proto import wandb_internal_pb2 as pb

    out = {}
    for data in records(path):
        rec = pb.Record()
        rec.ParseFromString(data)
        if rec.WhichOneof("record_type") == "metric" and rec.metric.step_metric:
            out[rec.metric.name or rec.metric.glob_name] = rec.metric.step_metric
    return out


def record_types(path) -> list[str]:
    """The kind of every record of the file, in order (what a test reports when something is missing)."""
    from wandb.proto import wandb_internal_pb2 as pb

    out = []
    for data in records(path):
        rec = pb.Record()
        rec.ParseFromString(data)
        out.append(rec.WhichOneof("record_type"))
    return out
