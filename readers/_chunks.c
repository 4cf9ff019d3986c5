/*
 * imupipe.readers._chunks: one decompressed MCAP chunk's sensor messages into the table, compiled.
 *
 * An MCAP chunk (https://mcap.dev/spec) holds message records: opcode 0x05, uint64 record
 * length, uint16 channel id, uint32 sequence, uint64 log_time, uint64 publish_time, then the
 * payload (31 bytes from the opcode). A ROS 2 sensor message's payload is little-endian CDR
 * (https://www.omg.org/spec/DDS-XTypes/1.3, 7.4.3): the 4-byte encapsulation header 00 01 00 00,
 * std_msgs/Header (int32 sec, uint32 nanosec, uint32 frame_id length n with its NUL, n bytes),
 * padding to 8 bytes counted from the end of the encapsulation header, then float64 fields
 * (imupipe.readers.cdr.FIELDS).
 *
 * The numpy path (imupipe.readers.mcap.fast.ChunkMessages.records, then
 * imupipe.readers.decoded.decode_piece, then imupipe.readers.table_buffer) reads a chunk in a
 * few dozen numpy calls: cheap per message, but about a millisecond per chunk of 2,850 Imu
 * messages, as long as the decompression of the chunk. Here the same work is two passes in C:
 *
 *   cdr_walk: the records of one channel checked (opcode, length, channel id) and found to hold
 *             one CDR layout (one payload size, encapsulation, frame_id), their times gathered;
 *   fill:     the float fields of those messages written straight into the table's columns,
 *             a column that holds only zeros so far left unwritten unless a value is not zero.
 *
 * and crc32, the CRC-32 a chunk record states over its decompressed bytes, by carry-less
 * multiplication (below), 4x zlib 1.2's speed.
 *
 * Anything else (another layout, a damaged record) makes cdr_walk return None and the numpy
 * path reads the chunk (and names what is wrong). imupipe.readers.chunk_fill holds the Python
 * side; tests/test_chunk_fill.py checks that both paths give the same tables, byte for byte.
 *
 * Only the CPython C API and the buffer protocol are used (no numpy C API).
 */
#define PY_SSIZE_T_CLEAN
#include <Python.h>
#include <stdint.h>
#include <string.h>

#define OP_MESSAGE 0x05
#define MESSAGE_HEADER 31 /* bytes from a message record's opcode to its payload */
#define MAX_SLOTS 63

static inline uint64_t rd64(const uint8_t *p) {
    uint64_t v;
    memcpy(&v, p, 8);
    return v; /* little-endian hosts only (setup.py builds on them; see chunk_fill.compiled) */
}

static inline uint32_t rd32(const uint8_t *p) {
    uint32_t v;
    memcpy(&v, p, 4);
    return v;
}

/* Whether the frame_id bytes a and b (n of them, room: the payload's bytes from a on, at least
 * n) are equal: a frame_id of 1 to 16 bytes (most are) compared with two 8-byte words, which
 * may overlap, instead of a call to memcmp per message; a word never reads past the payload. */
static inline int same_frame(const uint8_t *a, const uint8_t *b, Py_ssize_t n, Py_ssize_t room) {
    if (n == 0) return 1;
    if (n > 16 || (n < 8 && room < 8)) return memcmp(a, b, (size_t)n) == 0;
    if (n >= 8) return rd64(a) == rd64(b) && rd64(a + n - 8) == rd64(b + n - 8);
    const uint64_t mask = (1ULL << (8 * n)) - 1; /* n < 8: the first n bytes of a word */
    return ((rd64(a) ^ rd64(b)) & mask) == 0;
}

/* The loop of cdr_walk (without the GIL): 1 when every record at offsets matches the first
 * one's layout (its times written to out, ordered set), else 0. */
static int walk_records(const uint8_t *buf, Py_ssize_t len, const int64_t *offsets, Py_ssize_t n,
                        unsigned int channel, uint64_t reclen, Py_ssize_t size, const uint8_t *p0,
                        Py_ssize_t frame_len, int64_t *out, int *ordered_out) {
    const uint32_t encap = rd32(p0), strlen_ = rd32(p0 + 12);
    int ordered = 3;
    for (Py_ssize_t i = 0; i < n; i++) {
        const int64_t o = offsets[i];
        if (o < 0 || o > len - MESSAGE_HEADER - size) return 0;
        const uint8_t *r = buf + o;
        if (r[0] != OP_MESSAGE || rd64(r + 1) != reclen ||
            (unsigned int)(r[9] | (r[10] << 8)) != channel)
            return 0;
        const uint8_t *p = r + MESSAGE_HEADER;
        /* encapsulation, string length, then the frame_id's bytes (its NUL not compared: the
         * numpy path does not either) */
        if (rd32(p) != encap || rd32(p + 12) != strlen_ ||
            !same_frame(p + 16, p0 + 16, frame_len, size - 16))
            return 0;
        int64_t log, pub;
        memcpy(&log, r + 15, 8);
        memcpy(&pub, r + 23, 8);
        int32_t sec;
        memcpy(&sec, p + 4, 4);
        const int64_t stamp = (int64_t)sec * 1000000000LL + (int64_t)rd32(p + 8);
        if (i) {
            if (log < out[i - 1]) ordered &= ~1;
            if (stamp < out[2 * n + i - 1]) ordered &= ~2;
        }
        out[i] = log;
        out[n + i] = pub;
        out[2 * n + i] = stamp;
    }
    *ordered_out = ordered;
    return 1;
}

/* cdr_walk(buf, offsets, channel, floats)
 * cdr_walk(buf, offsets, channel, floats, out)
 *     -> None | (times: bytearray or out, skip: int, frame: bytes, ordered: int)
 *
 * offsets: int64 byte offsets of channel's message records in buf (a decompressed chunk).
 * When every record is a message record of that channel lying whole in buf, every payload has
 * the first one's size, its encapsulation header (little-endian CDR), string length and
 * frame_id bytes, and room for `floats` float64 fields after the header: times holds 3 * n
 * int64 (log times, publish times, header stamps sec * 1e9 + nanosec, each n long; the uint64
 * times read as int64), skip the bytes from a record's opcode to its first float field, frame
 * the frame_id's bytes (without the NUL), ordered bit 0 set when the log times never decrease,
 * bit 1 when the header stamps never do. Else None (the numpy path reads the chunk). out
 * (optional): a writable buffer of at least 3 * n int64 to write the times into instead of a
 * new bytearray (returned as times). */
static PyObject *cdr_walk(PyObject *self, PyObject *args) {
    Py_buffer view, offs, given = {0};
    unsigned int channel;
    Py_ssize_t floats;
    PyObject *dest = NULL;
    if (!PyArg_ParseTuple(args, "y*y*In|O", &view, &offs, &channel, &floats, &dest)) return NULL;
    if (dest == Py_None) dest = NULL;
    const uint8_t *buf = (const uint8_t *)view.buf;
    const Py_ssize_t len = view.len;
    const Py_ssize_t n = offs.len / (Py_ssize_t)sizeof(int64_t);
    const char *raw = (const char *)offs.buf;
    PyObject *result = NULL;
    int64_t o0;
    if (n == 0 || floats < 0) goto none;
    memcpy(&o0, raw, sizeof(int64_t));
    if (o0 < 0 || o0 + MESSAGE_HEADER + 16 > len) goto none;
    const uint64_t reclen = rd64(buf + o0 + 1);
    if (reclen < MESSAGE_HEADER - 9 + 16 || reclen > (uint64_t)len) goto none;
    const Py_ssize_t size = (Py_ssize_t)reclen - (MESSAGE_HEADER - 9); /* payload bytes */
    const uint8_t *p0 = buf + o0 + MESSAGE_HEADER;
    const uint32_t encap = rd32(p0), strlen_ = rd32(p0 + 12);
    if (encap != 0x100u || strlen_ < 1 || (Py_ssize_t)strlen_ > size) goto none;
    Py_ssize_t body = 12 + (Py_ssize_t)strlen_;
    const Py_ssize_t first = 4 + body + ((8 - body % 8) % 8);
    if (first + 8 * floats > size) goto none;
    const Py_ssize_t frame_len = (Py_ssize_t)strlen_ - 1;
    PyObject *times;
    int64_t *out;
    if (dest != NULL) { /* the caller's buffer (used again from one call to the next) */
        if (PyObject_GetBuffer(dest, &given, PyBUF_WRITABLE | PyBUF_C_CONTIGUOUS) < 0) goto fail;
        if (given.len < 3 * n * (Py_ssize_t)sizeof(int64_t)) {
            PyBuffer_Release(&given);
            PyErr_SetString(PyExc_ValueError, "cdr_walk: out holds fewer than 3 * n int64");
            goto fail;
        }
        times = dest;
        Py_INCREF(times);
        out = (int64_t *)given.buf;
    } else {
        times = PyByteArray_FromStringAndSize(NULL, 3 * n * (Py_ssize_t)sizeof(int64_t));
        if (times == NULL) goto fail;
        out = (int64_t *)PyByteArray_AS_STRING(times);
    }
    int ordered = 0;
    int ok;
    Py_BEGIN_ALLOW_THREADS /* the buffers are held: other threads may run meanwhile */
    ok = walk_records(buf, len, (const int64_t *)raw, n, channel, reclen, size, p0, frame_len,
                      out, &ordered);
    Py_END_ALLOW_THREADS
    if (dest != NULL) PyBuffer_Release(&given);
    if (!ok) goto drop;
    result = Py_BuildValue("NnNi", times, (Py_ssize_t)(MESSAGE_HEADER + first),
                           PyBytes_FromStringAndSize((const char *)p0 + 16, frame_len), ordered);
    goto done;
drop:
    Py_DECREF(times);
none:
    result = Py_None;
    Py_INCREF(result);
    goto done;
fail:
    result = NULL;
done:
    PyBuffer_Release(&view);
    PyBuffer_Release(&offs);
    return result;
}

#define FILL_BLOCK 128 /* messages per block: their records stay in L1/L2 across the slots */

static inline int is_nan(uint64_t v) {
    return (v & 0x7fffffffffffffffULL) > 0x7ff0000000000000ULL;
}

/* One block of nb messages (record offsets at, first row row0) written slot by slot: a tight
 * loop per column instead of every column per message (the same bytes: a clean slot is
 * written from its first message whose values are not all +0.0, as message by message). */
static void fill_block(const uint8_t *buf, const int64_t *at, int64_t nb, Py_ssize_t skip,
                       const int64_t *slots, Py_ssize_t m, Py_buffer *dst, int64_t row0,
                       unsigned long long *clean, unsigned long long *dirty,
                       unsigned long long nan_check, unsigned long long *nan) {
    for (Py_ssize_t s = 0; s < m; s++) {
        const int64_t c = slots[2 * s + 1];
        const Py_ssize_t off = skip + 8 * (Py_ssize_t)slots[2 * s];
        const unsigned long long bit = 1ULL << s;
        uint64_t *out = (uint64_t *)dst[s].buf + row0 * c;
        int64_t j0 = 0;
        if (*clean & bit) { /* zeros so far: the first message with a value not +0.0 */
            for (; j0 < nb; j0++) {
                const uint8_t *src = buf + at[j0] + off;
                uint64_t any = 0;
                for (int64_t e = 0; e < c; e++) any |= rd64(src + 8 * e);
                if (any) break;
            }
            if (j0 == nb) continue; /* the column holds zeros there already */
            *clean &= ~bit;
            *dirty |= bit;
        }
        if (c == 1) {
            for (int64_t j = j0; j < nb; j++) out[j] = rd64(buf + at[j] + off);
        } else if (c == 9) { /* covariances: a constant size, copied inline */
            for (int64_t j = j0; j < nb; j++) memcpy(out + 9 * j, buf + at[j] + off, 72);
        } else {
            for (int64_t j = j0; j < nb; j++)
                memcpy(out + c * j, buf + at[j] + off, (size_t)(8 * c));
        }
        if ((nan_check & bit) && !(*nan & bit)) {
            for (int64_t e = j0 * c; e < nb * c; e++)
                if (is_nan(out[e])) {
                    *nan |= bit;
                    break;
                }
        }
    }
}

/* fill(buf, offsets, skip, slots, columns, clean, nan_check, runs) -> (dirty, nan)
 *
 * For each message record at int64 offset o of offsets, its float fields start at o + skip.
 * slots: int64 pairs (first float, count), one per column; columns: one writable, C-contiguous
 * float64 buffer per slot, whose row r is at r * count. runs: int64 triples (first message,
 * first row, messages): message j of a run goes to row (first row + j - first message).
 * A slot whose bit is set in `clean` (a column holding zeros) is written only from the first
 * value that is not +0.0 bit for bit (the rows before are zeros already): its bit in dirty
 * says it was. A slot whose bit is set in nan_check has its bit in nan set when a value is
 * NaN. Every offset and row is checked against its buffer (IndexError). */
static PyObject *fill(PyObject *self, PyObject *args) {
    Py_buffer view, offs, slot_buf, run_buf;
    PyObject *columns;
    Py_ssize_t skip;
    unsigned long long clean, nan_check;
    if (!PyArg_ParseTuple(args, "y*y*ny*OKKy*", &view, &offs, &skip, &slot_buf, &columns, &clean,
                          &nan_check, &run_buf))
        return NULL;
    Py_buffer dst[MAX_SLOTS];
    Py_ssize_t n_dst = 0;
    PyObject *result = NULL;
    const Py_ssize_t m = slot_buf.len / (Py_ssize_t)(2 * sizeof(int64_t));
    const int64_t *slots = (const int64_t *)slot_buf.buf;
    if (!PyTuple_Check(columns) || PyTuple_GET_SIZE(columns) != m || m > MAX_SLOTS || skip < 0) {
        PyErr_SetString(PyExc_ValueError, "fill: one column per slot, at most 63, skip >= 0");
        goto done;
    }
    int64_t span = 0; /* bytes of float fields after skip that the slots read */
    for (Py_ssize_t s = 0; s < m; s++) {
        if (slots[2 * s] < 0 || slots[2 * s + 1] < 1) {
            PyErr_SetString(PyExc_ValueError, "fill: bad slot");
            goto done;
        }
        int64_t end = 8 * (slots[2 * s] + slots[2 * s + 1]);
        if (end > span) span = end;
        if (PyObject_GetBuffer(PyTuple_GET_ITEM(columns, s), &dst[s],
                               PyBUF_WRITABLE | PyBUF_C_CONTIGUOUS) < 0)
            goto done;
        n_dst++;
        if (dst[s].itemsize != 8 && dst[s].itemsize != 1) {
            PyErr_SetString(PyExc_ValueError, "fill: columns must be float64");
            goto done;
        }
    }
    const uint8_t *buf = (const uint8_t *)view.buf;
    const Py_ssize_t len = view.len;
    const Py_ssize_t n = offs.len / (Py_ssize_t)sizeof(int64_t);
    const char *raw = (const char *)offs.buf;
    const Py_ssize_t n_runs = run_buf.len / (Py_ssize_t)(3 * sizeof(int64_t));
    const int64_t *runs = (const int64_t *)run_buf.buf;
    const int64_t *at = (const int64_t *)raw; /* numpy's int64 array: aligned */
    for (Py_ssize_t k = 0; k < n_runs; k++) { /* every run, row and offset checked first */
        const int64_t a = runs[3 * k], row0 = runs[3 * k + 1], count = runs[3 * k + 2];
        if (a < 0 || count < 0 || a + count > n || row0 < 0) {
            PyErr_SetString(PyExc_IndexError, "fill: run outside the messages");
            goto done;
        }
        for (Py_ssize_t s = 0; s < m; s++) {
            if ((row0 + count) * slots[2 * s + 1] * 8 > dst[s].len) {
                PyErr_SetString(PyExc_IndexError, "fill: row outside its column");
                goto done;
            }
        }
        for (int64_t j = a; j < a + count; j++) {
            if (at[j] < 0 || at[j] + skip + span > len) {
                PyErr_Format(PyExc_IndexError, "fill: offset %lld out of the buffer",
                             (long long)at[j]);
                goto done;
            }
        }
    }
    unsigned long long dirty = 0, nan = 0;
    Py_BEGIN_ALLOW_THREADS /* the buffers are held: other threads may run meanwhile */
    for (Py_ssize_t k = 0; k < n_runs; k++) {
        const int64_t a = runs[3 * k], row0 = runs[3 * k + 1], count = runs[3 * k + 2];
        for (int64_t b = 0; b < count; b += FILL_BLOCK) {
            const int64_t nb = count - b < FILL_BLOCK ? count - b : FILL_BLOCK;
            fill_block(buf, at + a + b, nb, skip, slots, m, dst, row0 + b, &clean, &dirty,
                       nan_check, &nan);
        }
    }
    Py_END_ALLOW_THREADS
    result = Py_BuildValue("KK", dirty, nan);
done:
    for (Py_ssize_t s = 0; s < n_dst; s++) PyBuffer_Release(&dst[s]);
    PyBuffer_Release(&view);
    PyBuffer_Release(&offs);
    PyBuffer_Release(&slot_buf);
    PyBuffer_Release(&run_buf);
    return result;
}

/* crc32(data, crc=0) -> int | None: zlib.crc32(data, crc) (CRC-32 of IEEE 802.3 / ISO-HDLC,
 * reflected polynomial 0xEDB88320, the CRC an MCAP chunk record states), or None when this
 * CPU or build has no carry-less multiply (the caller then uses zlib.crc32).
 *
 * zlib 1.2's table-driven crc32 checks 2.4 GB/s here: 0.12-0.15 s of CPU for the 355 MB a
 * million Imu messages decompress to, as long as their zstd decompression. With PCLMULQDQ the
 * data is folded 64 bytes at a time into four 128-bit remainders (V. Gopal, E. Ozturk et al.,
 * "Fast CRC Computation for Generic Polynomials Using PCLMULQDQ Instruction", Intel, 2009):
 * a remainder r followed by d bits of data is replaced by r_hi * (x^(d+64) mod P) xor
 * r_lo * (x^d mod P), in the bit-reflected domain; the folding constants are those of the
 * Linux kernel's crc32-pclmul (arch/x86/crypto/crc32-pclmul_asm.S, R1-R4). The last 128-bit
 * remainder, taken as 16 bytes of message, and the bytes after it are finished a byte at a time
 * from a table: a CRC register of zero that reads those bytes ends where the register over the
 * whole data would, since the fold keeps the remainder modulo P (tests/test_chunk_fill.py
 * checks it against zlib.crc32 for every length from 0 to 300 bytes, at every alignment, and
 * on large buffers). The GIL is released meanwhile. */
static uint32_t crc_table[256];

static void crc_table_init(void) {
    for (uint32_t i = 0; i < 256; i++) {
        uint32_t c = i;
        for (int k = 0; k < 8; k++) c = c & 1 ? (c >> 1) ^ 0xEDB88320u : c >> 1;
        crc_table[i] = c;
    }
}

static inline uint32_t crc_bytes(uint32_t c, const uint8_t *p, size_t n) {
    for (size_t i = 0; i < n; i++) c = crc_table[(c ^ p[i]) & 0xff] ^ (c >> 8);
    return c;
}

#if (defined(__x86_64__) || defined(__i386__)) && (defined(__GNUC__) || defined(__clang__))
#include <immintrin.h>
#define HAVE_CLMUL 1

__attribute__((target("pclmul,sse2"))) static inline __m128i fold(__m128i x, __m128i k,
                                                                  __m128i data) {
    return _mm_xor_si128(_mm_xor_si128(_mm_clmulepi64_si128(x, k, 0x00),
                                       _mm_clmulepi64_si128(x, k, 0x11)),
                         data);
}

/* The CRC register (not inverted) after reading p[0:n], n >= 64, from register c. */
__attribute__((target("pclmul,sse2"))) static uint32_t crc_clmul(uint32_t c, const uint8_t *p,
                                                                 size_t n) {
    const __m128i k12 = _mm_set_epi64x(0x1c6e41596LL, 0x154442bd4LL); /* 4 x 128 bits on */
    const __m128i k34 = _mm_set_epi64x(0x0ccaa009eLL, 0x1751997d0LL); /* 128 bits on */
    __m128i x0 = _mm_loadu_si128((const __m128i *)p);
    __m128i x1 = _mm_loadu_si128((const __m128i *)(p + 16));
    __m128i x2 = _mm_loadu_si128((const __m128i *)(p + 32));
    __m128i x3 = _mm_loadu_si128((const __m128i *)(p + 48));
    x0 = _mm_xor_si128(x0, _mm_cvtsi32_si128((int)c)); /* the register enters with the data */
    p += 64;
    n -= 64;
    for (; n >= 64; p += 64, n -= 64) {
        x0 = fold(x0, k12, _mm_loadu_si128((const __m128i *)p));
        x1 = fold(x1, k12, _mm_loadu_si128((const __m128i *)(p + 16)));
        x2 = fold(x2, k12, _mm_loadu_si128((const __m128i *)(p + 32)));
        x3 = fold(x3, k12, _mm_loadu_si128((const __m128i *)(p + 48)));
    }
    x0 = fold(x0, k34, x1);
    x0 = fold(x0, k34, x2);
    x0 = fold(x0, k34, x3);
    for (; n >= 16; p += 16, n -= 16) x0 = fold(x0, k34, _mm_loadu_si128((const __m128i *)p));
    uint8_t rest[16];
    _mm_storeu_si128((__m128i *)rest, x0);
    return crc_bytes(crc_bytes(0, rest, 16), p, n);
}
#else
#define HAVE_CLMUL 0
#endif

static int clmul_ok(void) {
#if HAVE_CLMUL
    static int ok = -1;
    if (ok < 0) {
        __builtin_cpu_init();
        ok = __builtin_cpu_supports("pclmul") && __builtin_cpu_supports("sse2");
    }
    return ok;
#else
    return 0;
#endif
}

static PyObject *crc32(PyObject *self, PyObject *args) {
    Py_buffer view;
    unsigned int start = 0;
    if (!PyArg_ParseTuple(args, "y*|I", &view, &start)) return NULL;
    if (!clmul_ok()) {
        PyBuffer_Release(&view);
        Py_RETURN_NONE;
    }
    const uint8_t *p = (const uint8_t *)view.buf;
    const size_t n = (size_t)view.len;
    uint32_t c = ~(uint32_t)start;
    if (n < 64) {
        c = crc_bytes(c, p, n);
    } else {
        Py_BEGIN_ALLOW_THREADS
#if HAVE_CLMUL
        c = crc_clmul(c, p, n);
#endif
        Py_END_ALLOW_THREADS
    }
    PyBuffer_Release(&view);
    return PyLong_FromUnsignedLong((unsigned long)~c);
}

static PyMethodDef methods[] = {
    {"cdr_walk", cdr_walk, METH_VARARGS,
     "cdr_walk(buf, offsets, channel, floats, out=None) -> None | (times, skip, frame, ordered): one "
     "channel's message records of one little-endian CDR layout, checked, and their times."},
    {"fill", fill, METH_VARARGS,
     "fill(buf, offsets, skip, slots, columns, clean, nan_check, runs) -> (dirty, nan): the "
     "float fields of the messages written into the table's columns."},
    {"crc32", crc32, METH_VARARGS,
     "crc32(data, crc=0) -> int | None: zlib.crc32(data, crc) with carry-less multiplication, "
     "or None when the CPU has none."},
    {NULL, NULL, 0, NULL},
};

static struct PyModuleDef module = {
    PyModuleDef_HEAD_INIT, "_chunks",
    "One MCAP chunk's sensor messages into the table, compiled (imupipe.readers.chunk_fill).",
    -1, methods,
};

PyMODINIT_FUNC PyInit__chunks(void) {
    crc_table_init();
    return PyModule_Create(&module);
}
