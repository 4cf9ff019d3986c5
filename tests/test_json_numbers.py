"""JSON messages read by template (``readers/json_numbers.py``): value for value Python's ``json``
(``mcap``'s JSON decoder), whatever the shapes, number forms and bytes between the payloads; a
number outside JSON's grammar is a bad payload, named by its index."""

from __future__ import annotations

import json

import numpy as np
import pytest

from imupipe.readers import message_fields
from imupipe.readers.cdr import PayloadError
from imupipe.readers.message_fields import Leaf, json_type

SCHEMA = {
    "type": "object",
    "properties": {
        "t": {"type": "integer"},
        "g": {"type": "object", "properties": {k: {"type": "number"} for k in "xyz"}},
        "a": {"type": "array", "items": {"type": "number"}, "minItems": 3, "maxItems": 3},
    },
}
LEAVES = [Leaf(("t",)), *(Leaf(("g", k)) for k in "xyz"), *(Leaf(("a", i)) for i in range(3))]


def chunk(payloads: list[bytes], seed: int = 0) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The payloads in one buffer with random bytes (digits, quotes, dots...) between them, as
    record headers lie between the messages of an MCAP chunk."""
    rng = np.random.default_rng(seed)
    parts, starts, at = [], [], 0
    for p in payloads:
        junk = bytes(rng.choice(list(b'0123456789.eE+-"{}[], x'), int(rng.integers(0, 40))))
        parts += [junk, p]
        starts.append(at + len(junk))
        at += len(junk) + len(p)
    parts.append(b"7.e5")  # number characters right after the last payload
    buf = np.frombuffer(b"".join(parts), np.uint8).copy()
    return buf, np.array(starts), np.array([len(p) for p in payloads])


def number_text(rng: np.random.Generator) -> str:
    kind = int(rng.integers(0, 9))
    x = float(rng.normal(0, 10.0 ** int(rng.integers(-30, 30))))
    return [
        repr(x),
        f"{x:.3e}",
        f"{x:.17E}".replace("E+", "E"),
        str(int(rng.integers(-(10**12), 10**12))),
        "-0",
        "0.0",
        "1e-05",
        "123456789012345678901234567890",  # more digits than a double holds
        repr(float(np.float32(x))),
    ][kind]


def documents(n: int, seed: int = 1) -> list[bytes]:
    """Messages of several shapes: extra fields, numbers in strings and keys, escapes, nested
    lists, true/false/null, indentation, key order, duplicate keys."""
    rng = np.random.default_rng(seed)
    out = []
    for i in range(n):
        g = ", ".join(f'"{k}": {number_text(rng)}' for k in "xyz")
        a = ", ".join(number_text(rng) for _ in range(3))
        t = str(10**18 + i * 2_500_000 + int(rng.integers(0, 1000)))
        shape = i % 9 if i % 2 else 0  # half of the messages have the first shape
        if shape == 0:
            text = f'{{"t": {t}, "g": {{{g}}}, "a": [{a}]}}'
        elif shape == 1:
            text = f'{{"frame_id": "imu_12", "t": {t}, "g": {{{g}}}, "a": [{a}], "ok": true}}'
        elif shape == 2:
            text = f'{{"a": [{a}],"g":{{{g}}},"t":{t},"cov":[[1,2e3],[-3.5,null]]}}'
        elif shape == 3:
            text = f'{{"note": "say \\"12\\" or 1.e5 \\\\", "t": {t}, "g": {{{g}}}, "a": [{a}]}}'
        elif shape == 4:
            text = json.dumps(json.loads(f'{{"t": {t}, "g": {{{g}}}, "a": [{a}]}}'), indent=2)
        elif shape == 5:
            text = f'{{"t": 5, "t": {t}, "g": {{{g}}}, "a": [{a}], "k1e5": -1}}'  # last t wins
        elif shape == 6:
            text = f' \t{{"t":{t},"g":{{{g}}},"a":[{a}],"u":"\\u00e9\u00e9 9"}}\r\n'
        elif shape == 7:
            text = f'{{"t": {t}, "g": {{{g}}}, "a": [{a}], "more": [{a}, {a}]}}'
        else:
            text = f'{{"t": {t}, "a": [{a}], "g": {{{g}}}, "s": "x{i % 3}"}}'
        out.append(text.encode())
    return out


def decode_both(payloads: list[bytes], seed: int = 0) -> tuple[list, list]:
    mtype = json_type("imu_json", json.dumps(SCHEMA).encode())
    buf, starts, lengths = chunk(payloads, seed)
    got = mtype.decode(buf, starts, lengths, LEAVES)
    ref = mtype.decode_reference(buf, starts, lengths, LEAVES)
    return got, ref


def test_values_are_jsons_whatever_the_shape(monkeypatch):
    payloads = documents(600)
    arrow_rows = []
    arrow = message_fields._decode_json_arrow

    def counting(mtype, buf, starts, lengths, leaves):  # noqa: ANN001, ANN202
        arrow_rows.append(len(starts))
        return arrow(mtype, buf, starts, lengths, leaves)

    monkeypatch.setattr(message_fields, "_decode_json_arrow", counting)
    got, ref = decode_both(payloads)
    for g, r, leaf in zip(got, ref, LEAVES, strict=True):
        r = np.asarray(r, g.dtype)
        assert g.dtype == (np.int64 if leaf.path == ("t",) else np.float64)
        assert np.array_equal(g.view(np.int64), r.view(np.int64)), leaf  # -0.0 too
    # the first 8 shapes by template; the 9th (s: "x0", "x1", "x2": three texts) by Arrow
    assert sum(arrow_rows) < len(payloads) // 9 + 10


def test_one_shape_takes_no_arrow(monkeypatch):
    payloads = [p for i, p in enumerate(documents(200)) if i % 2 == 0]
    monkeypatch.setattr(message_fields, "_decode_json_arrow", None)  # would fail if called
    got, ref = decode_both(payloads, seed=3)
    for g, r in zip(got, ref, strict=True):
        assert np.array_equal(g, np.asarray(r, g.dtype))


@pytest.mark.parametrize(
    "bad", ["01", "-01", "1.", "1.e5", "-", "+1", ".5", "-.5", "1e", "1e+", "0x1", "1..2", "nan"]
)
def test_a_number_outside_the_grammar_is_a_bad_payload(bad):
    payloads = [p for i, p in enumerate(documents(40)) if i % 2 == 0]
    text = payloads[13].decode()
    at = text.index('"a": [') + len('"a": [')
    payloads[13] = (text[:at] + bad + text[text.index(",", at) :]).encode()
    with pytest.raises(ValueError):
        json.loads(payloads[13])
    with pytest.raises(PayloadError) as err:
        decode_both(payloads)
    assert err.value.index == 13


def test_nan_and_infinity_read_as_json_reads_them():
    payloads = [p for i, p in enumerate(documents(40)) if i % 2 == 0]
    for k, word in ((3, "NaN"), (8, "Infinity"), (9, "-Infinity")):
        text = payloads[k].decode()
        at = text.index('"a": [') + len('"a": [')
        payloads[k] = (text[:at] + word + text[text.index(",", at) :]).encode()
    got, ref = decode_both(payloads)
    a0 = got[4]
    assert np.isnan(a0[3]) and a0[8] == np.inf and a0[9] == -np.inf
    for g, r in zip(got, ref, strict=True):
        assert np.array_equal(g, np.asarray(r, g.dtype), equal_nan=True)


def test_a_long_template_is_left_to_arrow(monkeypatch):
    from imupipe.readers import json_numbers

    payloads = [p for i, p in enumerate(documents(60)) if i % 2 == 0]
    monkeypatch.setattr(json_numbers, "MAX_NUMBERS", 6)  # the documents hold 7 numbers
    arrow_rows = []
    arrow = message_fields._decode_json_arrow

    def counting(mtype, buf, starts, lengths, leaves):  # noqa: ANN001, ANN202
        arrow_rows.append(len(starts))
        return arrow(mtype, buf, starts, lengths, leaves)

    monkeypatch.setattr(message_fields, "_decode_json_arrow", counting)
    got, ref = decode_both(payloads)
    assert arrow_rows == [len(payloads)]
    for g, r in zip(got, ref, strict=True):
        assert np.array_equal(g, np.asarray(r, g.dtype))
