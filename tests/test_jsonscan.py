"""The compiled JSON pass (``readers/_jsonscan.c``) against the numpy path and Python: the same
columns as ``IMUPIPE_PURE_PYTHON=1`` gives, bit for bit, and every number parsed as ``float()``
or ``int()`` parses it (correct rounding: subnormals, 17 and more digits, halfway cases, huge and
tiny exponents, every spelling of zero)."""

from __future__ import annotations

import json
import math
import random
import struct

import numpy as np
import pytest
from test_json_numbers import LEAVES, SCHEMA, chunk, documents, random_documents, random_number

from imupipe.readers import json_numbers
from imupipe.readers.message_fields import json_type
from imupipe.readers.record_walk import PURE_PYTHON_ENV

_jsonscan = pytest.importorskip(
    "imupipe.readers._jsonscan", reason="not built (python setup.py build_ext --inplace)"
)

EDGES = [
    "0",
    "-0",
    "0.0",
    "-0.0",
    "0e0",
    "-0e-0",
    "0E+5",
    "-0.000e99",
    "1",
    "-1",
    "9007199254740992",
    "9007199254740993",
    "9007199254740995",  # 2^53, ties to even
    "18446744073709551615",
    "18446744073709551616",
    "99999999999999999999",  # 19-20 digits
    "9223372036854775807",
    "-9223372036854775808",
    "9223372036854775808",  # int64 bounds
    "1e23",
    "8.98846567431158e307",
    "1.7976931348623157e308",
    "1.7976931348623158e308",
    "1.7976931348623159e308",
    "1e309",
    "-1e400",
    "1e99999999999",
    "1e-99999999999",
    "2.2250738585072011e-308",
    "2.2250738585072014e-308",
    "4.9406564584124654e-324",
    "2.4703282292062327e-324",
    "2.4703282292062328e-324",
    "5e-324",
    "1e-400",
    "0.1",
    "0.2",
    "0.30000000000000004",
    "123456789012345678901234567890",
    "7.2057594037927933e16",
    "2.0000000000000004440892098500626161694526672363281250001",
    "1.00000000000000011102230246251565404236316680908203125",  # exactly halfway: to even
    "1.00000000000000011102230246251565404236316680908203126",
    "0." + "0" * 400 + "1e400",
    "1" + "0" * 400 + "e-400",
]


def random_texts(n: int, seed: int) -> list[str]:
    """JSON numbers of every form (``test_json_numbers.random_number``) and doubles written
    with 15 to 40 significant digits (near halfway points)."""
    rng = random.Random(seed)
    texts = []
    while len(texts) < n:
        if rng.random() < 0.7:
            with np.errstate(over="ignore"):  # a float32 overflow: "inf", dropped below
                text = random_number(rng)
        else:
            x = struct.unpack("<d", rng.getrandbits(64).to_bytes(8, "little"))[0]
            text = f"{x:.{rng.randrange(14, 40)}e}" if math.isfinite(x) else "0"
        if text[-1].isdigit():  # not "inf" (a float32 overflow)
            texts.append(text)
    return texts


def parse(texts: list[str], integer: bool) -> tuple[np.ndarray, np.ndarray]:
    raw = [t.encode() for t in texts]
    lengths = np.array([len(r) for r in raw], np.int64)
    starts = np.cumsum(lengths) - lengths
    values, ok = _jsonscan.parse(b"".join(raw), starts, lengths, integer)
    return np.frombuffer(values, np.int64 if integer else np.float64), np.frombuffer(ok, bool)


def check_parse(texts: list[str]) -> None:
    values, ok = parse(texts, False)
    assert ok.all()
    ref = np.array([float(json.loads(t)) for t in texts])  # json: "-0" is the int 0
    wrong = np.flatnonzero(values.view(np.int64) != ref.view(np.int64))
    assert not len(wrong), [texts[i] for i in wrong[:5]]
    values, ok = parse(texts, True)
    for text, value, took in zip(texts, values.tolist(), ok.tolist(), strict=True):
        whole = not any(c in text for c in ".eE") and -(2**63) <= int(text) < 2**63
        assert took == whole, text
        assert not took or value == int(text), text


def test_edges_parse_as_float_and_int():
    check_parse(EDGES)


def test_random_numbers_parse_as_float_and_int():
    check_parse(random_texts(60_000, 7))


@pytest.mark.slow
def test_millions_of_random_numbers_parse_as_float():
    for seed in range(10):
        check_parse(random_texts(300_000, 100 + seed))


def test_not_json_numbers_are_refused():
    bad = [
        "01",
        "-01",
        "1.",
        "1.e5",
        "-",
        "+1",
        ".5",
        "-.5",
        "1e",
        "1e+",
        "0x1",
        "1..2",
        "nan",
        "Infinity",
        "1e5e5",
        "",
        " 1",
        "1 ",
        "--1",
        "1E-",
        "00",
    ]
    for integer in (False, True):
        assert not parse(bad, integer)[1].any()


def test_compiled_and_numpy_paths_give_the_same_columns(monkeypatch):
    """Whatever the shapes and numbers, the compiled pass gives the numpy path's columns bit
    for bit, and keeps the same templates for the channel's next chunk."""
    mtype = json_type("imu_json", json.dumps(SCHEMA).encode())
    matched = []

    class Counting:
        @staticmethod
        def match(*args):  # noqa: ANN002, ANN205
            matched.append(_jsonscan.match(*args))
            return matched[-1]

    for seed, payloads in enumerate([documents(600), *(random_documents(800, s) for s in (3, 4))]):
        buf, starts, lengths = chunk(payloads, seed)
        got = {}
        for path in ("numpy", "compiled"):
            if path == "numpy":
                monkeypatch.setenv(PURE_PYTHON_ENV, "1")
            else:
                monkeypatch.setattr(json_numbers, "_module", lambda: Counting)
            mtype.json_shapes.clear()
            got[path] = mtype.decode(buf, starts, lengths, LEAVES)
            kept = next(iter(mtype.json_shapes.values()))
            got[path + " shapes"] = [shape.text.tobytes() for shape in kept]
            monkeypatch.undo()
        for a, b in zip(got["numpy"], got["compiled"], strict=True):
            assert a.dtype == b.dtype
            assert np.array_equal(a.view(np.int64), b.view(np.int64))
        assert got["numpy shapes"] == got["compiled shapes"]
    assert sum(matched) > 1500  # the messages the compiled pass read


@pytest.mark.parametrize("bad", ["1e5e5", "1..2", "1e5.5", "2-3"])
def test_an_unmapped_number_the_numpy_path_lets_pass_is_a_bad_payload(bad, monkeypatch):
    """A slip in an unmapped number that only a full parse sees (the numpy path does not parse
    unmapped numbers) is seen by the compiled pass: its message goes to the reader that names
    it, as json would."""
    from imupipe.readers.cdr import PayloadError

    monkeypatch.delenv(PURE_PYTHON_ENV, raising=False)
    payloads = [p for p in random_documents(60, 5) if b'"cov"' in p]
    text = payloads[-3].decode()
    at = text.index('"cov": [[') + len('"cov": [[')
    payloads[-3] = (text[:at] + bad + text[text.index(",", at) :]).encode()
    with pytest.raises(ValueError):
        json.loads(payloads[-3])
    mtype = json_type("imu_json", json.dumps(SCHEMA).encode())
    buf, starts, lengths = chunk(payloads)
    with pytest.raises(PayloadError) as err:
        mtype.decode(buf, starts, lengths, LEAVES)
    assert err.value.index == len(payloads) - 3
