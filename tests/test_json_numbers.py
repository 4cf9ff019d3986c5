"""JSON messages read by template (``readers/json_numbers.py``): value for value Python's ``json``
(``mcap``'s JSON decoder), whatever the shapes, number forms and bytes between the payloads; a
number outside JSON's grammar is a bad payload, named by its index. Every test runs twice: with
the compiled pass (``readers/_jsonscan.c``) and with the numpy path (``IMUPIPE_PURE_PYTHON=1``);
``tests/test_jsonscan.py`` compares the two directly."""

from __future__ import annotations

import json
import math
import random
import struct

import numpy as np
import pytest

from imupipe.readers import json_numbers, message_fields
from imupipe.readers.cdr import PayloadError
from imupipe.readers.message_fields import Leaf, json_type
from imupipe.readers.record_walk import PURE_PYTHON_ENV

SCHEMA = {
    "type": "object",
    "properties": {
        "t": {"type": "integer"},
        "g": {"type": "object", "properties": {k: {"type": "number"} for k in "xyz"}},
        "a": {"type": "array", "items": {"type": "number"}, "minItems": 3, "maxItems": 3},
    },
}
LEAVES = [Leaf(("t",)), *(Leaf(("g", k)) for k in "xyz"), *(Leaf(("a", i)) for i in range(3))]


@pytest.fixture(autouse=True, params=["compiled", "numpy"])
def path(request, monkeypatch) -> str:  # noqa: ANN001
    """The compiled pass (skipped when it is not built) or the numpy path."""
    if request.param == "compiled":
        monkeypatch.delenv(PURE_PYTHON_ENV, raising=False)
        if not json_numbers.compiled():
            pytest.skip("imupipe.readers._jsonscan is not built (setup.py build_ext --inplace)")
    else:
        monkeypatch.setenv(PURE_PYTHON_ENV, "1")
    return request.param


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


@pytest.fixture
def arrow_rows(monkeypatch) -> list[int]:
    """The batch sizes handed to Arrow's JSON reader (the messages no template took)."""
    rows: list[int] = []
    arrow = message_fields._decode_json_arrow

    def counting(mtype, buf, starts, lengths, leaves):  # noqa: ANN001, ANN202
        rows.append(len(starts))
        return arrow(mtype, buf, starts, lengths, leaves)

    monkeypatch.setattr(message_fields, "_decode_json_arrow", counting)
    return rows


def test_values_are_jsons_whatever_the_shape(arrow_rows):
    payloads = documents(600)
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


def test_a_long_template_is_left_to_arrow(monkeypatch, arrow_rows):
    payloads = [p for i, p in enumerate(documents(60)) if i % 2 == 0]
    monkeypatch.setattr(json_numbers, "MAX_NUMBERS", 6)  # the documents hold 7 numbers
    got, ref = decode_both(payloads)
    assert arrow_rows == [len(payloads)]
    for g, r in zip(got, ref, strict=True):
        assert np.array_equal(g, np.asarray(r, g.dtype))


def random_number(rng: random.Random) -> str:
    """A JSON number (RFC 8259, section 6) of any form: shortest reprs of any double
    (subnormals, 17 digits, exponents both ways), float32 values, integers up to 25 digits,
    every spelling of zero, long mantissas, upper- and lower-case exponents with and without
    a sign."""
    kind = rng.randrange(7)
    if kind == 0:  # any finite double, from its bits
        x = struct.unpack("<d", rng.getrandbits(64).to_bytes(8, "little"))[0]
        return repr(x) if math.isfinite(x) else "1.7976931348623157e308"
    if kind == 1:
        return repr(float(np.float32(rng.gauss(0, 10.0 ** rng.randrange(-40, 39)))))
    if kind == 2:
        digits = str(rng.randrange(1, 10)) + "".join(rng.choices("0123456789", k=24))
        return ("-" if rng.random() < 0.5 else "") + digits[: rng.randrange(1, 26)]
    if kind == 3:
        return rng.choice(["0", "-0", "0.0", "-0.0", "0e0", "-0E-0", "0.000", "1E0"])
    mantissa = "".join(rng.choices("0123456789", k=rng.randrange(1, 30))).lstrip("0") or "0"
    text = ("-" if rng.random() < 0.5 else "") + mantissa
    if kind >= 5:
        text += "." + "".join(rng.choices("0123456789", k=rng.randrange(1, 25)))
    if kind != 5:
        text += rng.choice("eE") + rng.choice(["", "+", "-"]) + str(rng.randrange(330))
    return text


def random_documents(n: int, seed: int) -> list[bytes]:
    """Messages of a few shapes (so that templates repeat) with random numbers everywhere:
    the mapped ones, unmapped ones beside them, numbers in strings and keys, whitespace."""
    rng = random.Random(seed)
    out = []
    for _ in range(n):
        num = [random_number(rng) for _ in range(10)]
        t = str(rng.randrange(-(2**63), 2**63))
        shape = rng.randrange(5)
        if shape == 0:
            text = (
                f'{{"t": {t}, "g": {{"x": {num[0]}, "y": {num[1]}, "z": {num[2]}}}, '
                f'"a": [{num[3]}, {num[4]}, {num[5]}]}}'
            )
        elif shape == 1:
            text = (
                f'{{"id": "e{num[6]}", "q": [{num[6]},{num[7]}], "t":{t},"a":[{num[3]},'
                f'{num[4]},{num[5]}],"g":{{"z":{num[2]},"y":{num[1]},"x":{num[0]}}},"n":null}}'
            )
        elif shape == 2:
            text = (
                f'\n{{\r\n  "t" : {t} ,\t"g": {{"x":{num[0]},"y":{num[1]},"z":{num[2]},'
                f'"w":{num[8]}}},\n  "a": [ {num[3]} , {num[4]} , {num[5]} ], "b": true }}\n'
            )
        elif shape == 3:  # more numbers than mapped, in a nested list
            text = (
                f'{{"cov": [[{num[6]}, {num[7]}], [{num[8]}, {num[9]}]], "t": {t}, '
                f'"g": {{"x": {num[0]}, "y": {num[1]}, "z": {num[2]}}}, '
                f'"a": [{num[3]}, {num[4]}, {num[5]}], "k1.e5": "1.e5 -01"}}'
            )
        else:
            x = [float(v) if np.isfinite(float(v)) else 0.5 for v in num[:6]]
            text = json.dumps({"t": int(t), "g": dict(zip("xyz", x, strict=False)), "a": x[3:]})
        out.append(text.encode())
    return out


@pytest.mark.parametrize("seed", [11, 12, 13])
def test_random_numbers_read_as_json_reads_them(seed, monkeypatch):
    """Property test of the number scan: whatever the numbers' forms and the text around them,
    every value is json's, bit for bit, and most messages are read by template."""
    payloads = random_documents(1500, seed)
    arrow_rows: list[int] = []
    arrow = message_fields._decode_json_arrow

    def counting(mtype, buf, starts, lengths, leaves):  # noqa: ANN001, ANN202
        arrow_rows.append(len(starts))
        return arrow(mtype, buf, starts, lengths, leaves)

    monkeypatch.setattr(message_fields, "_decode_json_arrow", counting)
    got, ref = decode_both(payloads, seed=seed)
    for g, r, leaf in zip(got, ref, LEAVES, strict=True):
        r = np.asarray(r, g.dtype)
        assert np.array_equal(g.view(np.int64), r.view(np.int64)), leaf
    # by template but the fifth of the messages whose "id" string is random
    assert sum(arrow_rows) < 0.3 * len(payloads)


@pytest.mark.parametrize("where", ["mapped", "unmapped"])
@pytest.mark.parametrize("bad", ["01", "-01", "1.", "1.e5", "-", "+1", ".5", "-.5", "-0.E1"])
def test_a_bad_number_mapped_or_not_names_its_message(bad, where):
    """A number outside the grammar, mapped or not, makes its message a bad payload, named by
    its index in the batch."""
    payloads = [p for p in random_documents(60, 5) if b'"cov"' in p]
    text = payloads[-3].decode()
    key = '"a": [' if where == "mapped" else '"cov": [['
    at = text.index(key) + len(key)
    payloads[-3] = (text[:at] + bad + text[text.index(",", at) :]).encode()
    with pytest.raises(ValueError):
        json.loads(payloads[-3])
    with pytest.raises(PayloadError) as err:
        decode_both(payloads)
    assert err.value.index == len(payloads) - 3


def test_the_number_views_are_valid_arrow(monkeypatch, path):
    """The string_view arrays handed to Arrow's cast pass Arrow's full validation (inline
    numbers zero-padded, the prefix of the others their first 4 bytes)."""
    import pyarrow.compute as pc

    if path == "compiled":
        pytest.skip("the compiled pass hands no number to Arrow")

    cast = pc.cast
    checked = []

    def validating(array, *args, **kwargs):  # noqa: ANN001, ANN002, ANN003, ANN202
        array.validate(full=True)
        checked.append(len(array))
        return cast(array, *args, **kwargs)

    monkeypatch.setattr(pc, "cast", validating)
    got, ref = decode_both(random_documents(300, 21), seed=21)
    assert sum(checked) > 300
    for g, r in zip(got, ref, strict=True):
        assert np.array_equal(g.view(np.int64), np.asarray(r, g.dtype).view(np.int64))


def test_templates_carried_from_chunk_to_chunk(monkeypatch):
    """A channel's templates are tried first on its next chunk: right where they fit, harmless
    where none of that chunk's messages has their shape."""
    made = []
    of = json_numbers.Shape.of
    monkeypatch.setattr(json_numbers.Shape, "of", staticmethod(lambda *a: made.append(1) or of(*a)))
    mtype = json_type("imu_json", json.dumps(SCHEMA).encode())
    docs = documents(400, seed=4)
    shape = [i % 9 if i % 2 else 0 for i in range(len(docs))]  # as documents() draws them
    first = [p for p, s in zip(docs, shape, strict=True) if s == 1]  # one shape
    second = [p for p, s in zip(docs, shape, strict=True) if s in (1, 3, 7)]  # it and two others
    third = [p for p, s in zip(docs, shape, strict=True) if s == 5]  # none of those
    for k, (payloads, shapes, new) in enumerate(((first, 1, 1), (second, 3, 2), (third, 1, 1))):
        made.clear()
        buf, starts, lengths = chunk(payloads, seed=k)
        got = mtype.decode(buf, starts, lengths, LEAVES)
        ref = mtype.decode_reference(buf, starts, lengths, LEAVES)
        for g, r in zip(got, ref, strict=True):
            assert np.array_equal(g.view(np.int64), np.asarray(r, g.dtype).view(np.int64))
        # templates made from this chunk's messages, and the shapes kept for the next chunk
        assert len(made) == new
        assert len(mtype.json_shapes[tuple(leaf.path for leaf in LEAVES)]) == shapes
