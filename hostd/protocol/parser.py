"""Parse one line from a g2core board into a typed message.

`parse_line` never raises: whatever the bytes (invalid UTF-8, NULs, broken
or absurdly nested JSON), the answer is a message, at worst `Unparseable`
carrying the raw bytes. The daemon decides what a bad line means; the
parser only says what it is.
"""

from __future__ import annotations

import json
import re
from typing import Any, TypeGuard

from hostd.protocol.messages import (
    Ack,
    Banner,
    ExceptionReport,
    JsonObject,
    Message,
    Notice,
    QueueReport,
    Response,
    StatusReport,
    TextLine,
    Unparseable,
)

_BANNER_MSG = "SYSTEM READY"
# Printable text may carry TAB; any other C0 control byte (or DEL) is line noise.
_NOISE = frozenset(range(0x20)) - {0x09} | {0x7F}


# The answer to almost every job line, read without the JSON parser: an empty body, or
# at jv 4 the line's N word echoed (`{"r":{"n":120},"f":[1,0,18]}`; json_print_response).
_PLAIN_ANSWER = re.compile(rb'\{"r":\{(?:"n":(\d{1,10}))?\},"f":\[1,(\d{1,3}),(\d{1,4})\]\}')


# The match itself, for the session's per-line path: groups 2 and 3 are the footer's
# status and count, group 1 the echoed N.
plain_answer = _PLAIN_ANSWER.fullmatch


def parse_line(raw: bytes) -> Message:
    """Classify one line (terminator already removed)."""
    plain = _PLAIN_ANSWER.fullmatch(raw)
    if plain is not None:
        body = {} if plain[1] is None else {"n": int(plain[1])}
        return Response(body, int(plain[2]), int(plain[3]), raw)
    if raw[:1] == b"{":
        return _parse_json(raw)
    return _parse_text(raw)


def _parse_text(raw: bytes) -> Message:
    try:
        text = raw.decode("utf-8")
    except UnicodeDecodeError:
        return Unparseable("not valid UTF-8", raw)
    if any(ord(c) in _NOISE for c in text):
        return Unparseable("control characters in a text line", raw)
    return TextLine(text, raw)


def _parse_json(raw: bytes) -> Message:
    try:
        obj = json.loads(raw, parse_constant=_no_number)
    except (ValueError, RecursionError):  # UnicodeDecodeError is a ValueError
        obj = _loads_firmware_forms(raw)
        if obj is None:
            return Unparseable("malformed JSON", raw)
    if not isinstance(obj, dict):
        return Unparseable("JSON that is not an object", raw)
    if "r" in obj:
        return _parse_response(obj, raw)
    if len(obj) == 1:
        if "sr" in obj:
            sr = obj["sr"]
            if isinstance(sr, dict):
                return StatusReport(sr, raw)
            return Unparseable("status report that is not an object", raw)
        if "er" in obj:
            return _parse_exception(obj["er"], raw)
        if obj.get("ack") is True:
            return Ack(raw)
    if "qr" in obj and obj.keys() <= {"qr", "qi", "qo"}:
        return _parse_queue_report(obj, raw)
    return Notice(obj, raw)


# One token of a line as the firmware prints it: a JSON string, the punctuation,
# or a bare word (a number, a JSON literal, or what strict JSON would refuse).
_TOKEN = re.compile(r'"(?:[^"\\]|\\.)*"|[{}\[\]:,]|[^\s{}\[\]:,"]+|\s+')
_JSON_WORD = re.compile(r"true|false|null|-?(?:0|[1-9]\d*)(?:\.\d+)?(?:[eE][+-]?\d+)?")
# What the firmware's printf prints for a float that is not a number (report.cpp,
# json_parser.cpp `%f` of NaN and infinities): read as null, an unknown value.
_NOT_A_NUMBER = frozenset({"nan", "-nan", "inf", "-inf", "+inf", "+nan"})


def _loads_firmware_forms(raw: bytes) -> Any:
    """Strict JSON failed: read the forms real boards print, or None if it is still not JSON.

    Bare `nan` and `inf` (any case, signed) become null; an unquoted word that is
    not a number nor a JSON literal (older builds print some strings bare) becomes
    a string. Only the slow path: a line strict JSON reads never comes here.
    """
    try:
        text = raw.decode("utf-8")
    except UnicodeDecodeError:
        return None
    out: list[str] = []
    pos = 0
    for m in _TOKEN.finditer(text):
        if m.start() != pos:
            return None  # a stray quote: not something the firmware prints
        token = m.group()
        pos = m.end()
        if token[0] in '"{}[]:,' or token.isspace() or _JSON_WORD.fullmatch(token):
            out.append(token)
        elif token.lower() in _NOT_A_NUMBER:
            out.append("null")
        else:
            out.append(json.dumps(token))
    if pos != len(text):
        return None
    try:
        return json.loads("".join(out), parse_constant=_no_number)
    except (ValueError, RecursionError):
        return None


def _no_number(_constant: str) -> None:
    """NaN and the infinities are no value a client could use: null, as `nan` is."""
    return None


def _parse_response(obj: JsonObject, raw: bytes) -> Message:
    body = obj["r"]
    if not isinstance(body, dict):
        return Unparseable("response body that is not an object", raw)
    # Some TinyG builds nest the footer inside the body.
    footer = obj.get("f", body.get("f"))
    if not isinstance(footer, list) or len(footer) < 3 or not all(_is_int(v) for v in footer[:3]):
        return Unparseable("response without a valid footer", raw)
    if body.get("msg") == _BANNER_MSG:
        return Banner(
            fv=_number(body.get("fv")),
            fb=_number(body.get("fb")),
            hp=_scalar(body.get("hp")),
            hv=_scalar(body.get("hv")),
            id=body["id"] if isinstance(body.get("id"), str) else None,
            body=body,
            raw=raw,
        )
    return Response(body, footer[1], footer[2], raw)


def _parse_exception(er: Any, raw: bytes) -> Message:
    if not isinstance(er, dict):
        return Unparseable("exception report that is not an object", raw)
    st = er.get("st")
    msg = er.get("msg")
    return ExceptionReport(
        status=st if _is_int(st) else None,
        message=msg if isinstance(msg, str) else "",
        fields=er,
        raw=raw,
    )


def _parse_queue_report(obj: JsonObject, raw: bytes) -> Message:
    qr, qi, qo = obj.get("qr"), obj.get("qi"), obj.get("qo")
    if not _is_int(qr) or not all(v is None or _is_int(v) for v in (qi, qo)):
        return Unparseable("queue report with non-integer counts", raw)
    return QueueReport(qr, qi, qo, raw)


def _is_int(v: Any) -> TypeGuard[int]:
    return isinstance(v, int) and not isinstance(v, bool)


def _number(v: Any) -> float | None:
    if isinstance(v, int | float) and not isinstance(v, bool):
        return float(v)
    return None


def _scalar(v: Any) -> str | int | None:
    if isinstance(v, str):
        return v
    if _is_int(v):
        return v
    if isinstance(v, float):
        return int(v) if v.is_integer() else str(v)
    return None
