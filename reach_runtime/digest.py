"""The digest of an exported filter: SHA-256 over everything in the file but the digest itself.

An exported filter (``reach export``) is trusted as a checkpoint is: the file carries the SHA-256
of its contents, and a file whose digest is missing or does not match is refused before anything
in it is used. Without it an edited weight would load and decide differently, and an edited
``reach.time_range`` would let the runtime decide at times the network never covered.

**Definition.** An ONNX file is a serialized ``ModelProto``: a sequence of top-level fields (tag,
then payload). Its metadata is the repeated field 14 (``metadata_props``), each entry a message
of a key (field 1) and a value (field 2). The digest is stored in the entry whose key is
:data:`DIGEST_KEY`, as a JSON string ``"sha256:<64 hex digits>"`` (every ``reach.*`` value is
JSON). It is the SHA-256 of the file's bytes with that one entry's top-level field removed: the
other fields' bytes (graph, weights, opset, every other metadata entry), exactly as they lie in the
file, in their order. So the definition needs no ONNX library and no canonical re-serialization:
this module reads the protobuf wire format with the standard library alone, and any binding (C,
C++) can check a file the same way. A file re-serialized by another tool keeps a valid digest only
where the tool writes the same bytes; otherwise it is refused, which is the safe side.

The digest detects a changed file (an edited weight or metadata entry, a truncated or damaged
file); it is not a signature: whoever can write the file can also write a new digest.
"""

from __future__ import annotations

import hashlib
import json

__all__ = ["DIGEST_KEY", "ModelBytes", "read_model", "seal"]

#: the metadata key that holds an exported filter's digest
DIGEST_KEY = "reach.digest"

_METADATA_FIELD = 14  # ModelProto.metadata_props
_LENGTH_DELIMITED = 2


class _MalformedError(Exception):
    """The bytes are not a protobuf message (a truncated or foreign file)."""


def _varint(data: bytes | memoryview, pos: int) -> tuple[int, int]:
    """The varint at ``pos`` and the position after it."""
    value, shift = 0, 0
    while True:
        if pos >= len(data) or shift > 63:
            raise _MalformedError("a varint runs past the end")
        byte = data[pos]
        value |= (byte & 0x7F) << shift
        pos += 1
        if not byte & 0x80:
            return value, pos
        shift += 7


def _fields(data: bytes | memoryview) -> list[tuple[int, int, int, int, int]]:
    """``(field, wire type, start, payload start, end)`` per top-level field, in file order; for a
    length-delimited field the payload is ``data[payload start:end]``."""
    out = []
    pos = 0
    while pos < len(data):
        start = pos
        tag, pos = _varint(data, pos)
        field, wire = tag >> 3, tag & 7
        if field == 0:
            raise _MalformedError("a field numbered 0")
        if wire == 0:
            _, pos = _varint(data, pos)
            payload = pos
        elif wire == 1 or wire == 5:
            payload = pos
            pos += 8 if wire == 1 else 4
        elif wire == _LENGTH_DELIMITED:
            size, payload = _varint(data, pos)
            pos = payload + size
        else:
            raise _MalformedError(f"wire type {wire}")
        if pos > len(data):
            raise _MalformedError("a field runs past the end")
        out.append((field, wire, start, payload, pos))
    return out


def _entry(payload: memoryview) -> tuple[str, str]:
    """A ``StringStringEntryProto``'s key and value."""
    key, value = "", ""
    for field, wire, _, start, end in _fields(payload):
        if wire == _LENGTH_DELIMITED and field in (1, 2):
            text = bytes(payload[start:end]).decode("utf-8")
            key, value = (text, value) if field == 1 else (key, text)
    return key, value


class ModelBytes:
    """An ONNX file's bytes, parsed just enough for its digest: its metadata entries (key to value,
    as stored), the digest it carries (None where it carries none) and the one it should carry."""

    def __init__(self, data: bytes, where: str) -> None:
        self.data, self.where = data, where
        view = memoryview(data)
        self.metadata: dict[str, str] = {}
        self.stored: str | None = None
        hasher = hashlib.sha256()
        digests = 0
        try:
            fields = _fields(view)
            for field, wire, start, payload, end in fields:
                if field == _METADATA_FIELD and wire == _LENGTH_DELIMITED:
                    key, value = _entry(view[payload:end])
                    if key in self.metadata or (key == DIGEST_KEY and digests):
                        raise ValueError(f"{where}: metadata {key} appears more than once")
                    if key == DIGEST_KEY:
                        digests += 1
                        self.stored = value
                        continue
                    self.metadata[key] = value
                hasher.update(view[start:end])
        except (_MalformedError, UnicodeDecodeError) as error:
            raise ValueError(f"{where}: not a readable ONNX model (malformed protobuf: {error})") from None
        if not fields:
            raise ValueError(f"{where}: not a readable ONNX model (the file is empty)")
        self.computed = "sha256:" + hasher.hexdigest()

    def verify(self) -> str:
        """The file's digest, or one ``ValueError`` naming the file where it carries none or another."""
        if self.stored is None:
            raise ValueError(
                f"{self.where}: carries no digest ({DIGEST_KEY}), so nothing shows it is the file that was exported; "
                "export it again with `reach export`"
            )
        try:
            stored = json.loads(self.stored)
        except json.JSONDecodeError:
            stored = self.stored
        if stored != self.computed:
            raise ValueError(
                f"{self.where}: its digest ({DIGEST_KEY}) does not match its contents: the graph, its weights or "
                "its metadata changed after export; export it again with `reach export`"
            )
        return self.computed


def read_model(path: str) -> ModelBytes:
    """The file at ``path`` read once and parsed (:class:`ModelBytes`); the caller verifies it and
    hands the same bytes on, so the file checked is the file used. ``ValueError`` naming the file
    where it cannot be read or parsed."""
    try:
        with open(path, "rb") as handle:
            data = handle.read()
    except OSError as error:
        raise ValueError(f"{path}: cannot be read ({error.strerror or error})") from None
    return ModelBytes(data, path)


def _length(value: int) -> bytes:
    out = bytearray()
    while True:
        byte = value & 0x7F
        value >>= 7
        out.append(byte | (0x80 if value else 0))
        if not value:
            return bytes(out)


def _string_field(field: int, text: bytes) -> bytes:
    return _length(field << 3 | _LENGTH_DELIMITED) + _length(len(text)) + text


def seal(data: bytes, where: str = "model") -> bytes:
    """``data`` (a serialized ONNX model) with its digest: any digest entry it holds removed, and
    one appended that matches the rest (a repeated field may come in any order, so appending the
    entry adds it to ``metadata_props``)."""
    model = ModelBytes(data, where)
    view = memoryview(data)
    kept = bytearray()
    for field, wire, start, payload, end in _fields(view):
        if field == _METADATA_FIELD and wire == _LENGTH_DELIMITED and _entry(view[payload:end])[0] == DIGEST_KEY:
            continue
        kept += view[start:end]
    entry = _string_field(1, DIGEST_KEY.encode()) + _string_field(2, json.dumps(model.computed).encode())
    return bytes(kept) + _string_field(_METADATA_FIELD, entry)
