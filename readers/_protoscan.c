/*
 * imupipe.readers._protoscan: protobuf messages walked tag by tag, once each, and their mapped
 * fields written into the output columns (imupipe.readers.message_fields holds the Python side,
 * the plan, and the numpy fallback _ProtoScan).
 *
 * The wire format is the protobuf encoding spec's (https://protobuf.dev/programming-guides/
 * encoding/): a message is a run of (tag, value) records, tag = varint (field number << 3 |
 * wire type); wire type 0 a varint, 1 eight little-endian bytes, 2 a varint length and that
 * many bytes (a nested message, a packed run, a string...), 5 four little-endian bytes.
 *
 * The plan (message_fields._proto_plan) names, for each nested message on a mapped path (a
 * "struct", 0 the root), the field numbers wanted in it:
 *   fields: int64 rows (struct, number, kind, code, arg), sorted by struct;
 *     kind 0: a singular number, written to column arg;
 *     kind 1: a nested message, struct arg;
 *     kind 2: a repeated number, sequence arg;
 *     code: the decoding (CODE_* below), as the numpy path decodes it (a varint truncated to the
 *     field's width as numpy's assignment into an int32/uint32 array truncates, a bool 0 or 1,
 *     zigzag, a float widened to double bit for bit);
 *   seqs: int64 rows (first, width): elements 0..width-1 of a repeated number, element k going
 *     to column slots[first + k] (-1: not wanted).
 * Per message: absent fields stay 0 (proto3's default; the columns come zeroed), a singular
 * number seen twice keeps its last value (as protobuf parsers do), repeated numbers count
 * their elements packed or not, in order; a record of a mapped field number with another wire
 * type than the field's is an unknown field (as upb, protobuf's parser, takes it).
 *
 * A message this pass does not take exactly as the numpy path would is flagged (flags[i] = 1)
 * and left to it, which reads it or names what is wrong: a varint past 10 bytes or past its
 * message, a record past its message, wire types 3, 4, 6, 7, a packed run not a whole number of items, a nested message in two
 * records (protobuf merges them: the numpy path leaves it to protobuf's parser), fewer
 * elements than a mapped index, a payload outside the buffer. The loop runs without the GIL. Only the CPython C API
 * and the buffer protocol are used; tests/test_protoscan.py checks both paths give the same
 * columns, bit for bit, and the values against protobuf's own parser.
 */
#define PY_SSIZE_T_CLEAN
#include <Python.h>
#include <stdint.h>
#include <string.h>

#define MAX_STRUCTS 64
#define MAX_SEQS 64
#define MAX_FIELDS 1024
#define MAX_DEPTH 32

enum {
    CODE_VARINT_I64 = 0, /* int64 */
    CODE_VARINT_U64 = 1, /* uint64 (its bits as int64) */
    CODE_VARINT_I32 = 2, /* int32: the low 32 bits, sign-extended */
    CODE_VARINT_U32 = 3, /* uint32: the low 32 bits */
    CODE_VARINT_U8 = 4,  /* bool: 1 for any value but 0, as protobuf parses it */
    CODE_ZIGZAG_32 = 5,  /* sint32 */
    CODE_ZIGZAG_64 = 6,  /* sint64 */
    CODE_F64 = 7,        /* double */
    CODE_F32 = 8,        /* float, widened */
    CODE_U64 = 9,        /* fixed64 */
    CODE_U32 = 10,       /* fixed32 */
    CODE_I32 = 11,       /* sfixed32 */
    CODE_I64 = 12,       /* sfixed64 */
    N_CODES = 13
};

/* The wire type each code's field has (unpacked). */
static const int CODE_WIRE[N_CODES] = {0, 0, 0, 0, 0, 0, 0, 1, 5, 1, 5, 5, 1};

typedef struct {
    const uint8_t *buf;
    Py_ssize_t len;
    const int64_t *starts, *lengths;
    Py_ssize_t n;
    const int64_t *fields; /* n_fields rows of 5 */
    Py_ssize_t n_fields;
    Py_ssize_t first[MAX_STRUCTS], last[MAX_STRUCTS]; /* each struct's rows of fields */
    const int64_t *seqs, *slots;                      /* n_seqs rows of 2; the slots */
    Py_ssize_t n_seqs;
    int64_t *out; /* n_columns x n */
    Py_ssize_t n_columns;
    uint8_t *flags;
    /* per message */
    uint8_t seen[MAX_STRUCTS];
    int64_t count[MAX_SEQS];
    Py_ssize_t row;
} job;

/* The varint at *p (before e): 1 and *p moved past it, or 0 (past e or past 10 bytes). Bits
 * past 64 are dropped, as the numpy path's uint64 shifts drop them. */
static inline int varint(const uint8_t **p, const uint8_t *e, uint64_t *value) {
    const uint8_t *q = *p;
    uint64_t v = 0;
    for (int k = 0; k < 10; k++) {
        if (q >= e) return 0;
        uint8_t b = *q++;
        v |= (uint64_t)(b & 0x7F) << (7 * k);
        if (b < 0x80) {
            *p = q;
            *value = v;
            return 1;
        }
    }
    return 0;
}

static inline uint64_t load64(const uint8_t *p) {
    uint64_t v = 0;
    for (int k = 7; k >= 0; k--) v = (v << 8) | p[k];
    return v;
}

static inline uint32_t load32(const uint8_t *p) {
    return (uint32_t)p[0] | (uint32_t)p[1] << 8 | (uint32_t)p[2] << 16 | (uint32_t)p[3] << 24;
}

/* One item of code at *p (before e) as the column's 8 bytes; 0 when it does not fit. */
static inline int item(int code, const uint8_t **p, const uint8_t *e, int64_t *cell) {
    uint64_t raw;
    if (CODE_WIRE[code] == 0) {
        if (!varint(p, e, &raw)) return 0;
        switch (code) {
        case CODE_VARINT_I64:
        case CODE_VARINT_U64: *cell = (int64_t)raw; break;
        case CODE_VARINT_I32: *cell = (int64_t)(int32_t)(uint32_t)raw; break;
        case CODE_VARINT_U32: *cell = (int64_t)(uint32_t)raw; break;
        case CODE_VARINT_U8: *cell = raw != 0; break;
        case CODE_ZIGZAG_32: {
            uint64_t z = (raw >> 1) ^ (0 - (raw & 1));
            *cell = (int64_t)(int32_t)(uint32_t)z;
            break;
        }
        default: *cell = (int64_t)((raw >> 1) ^ (0 - (raw & 1))); break;
        }
        return 1;
    }
    Py_ssize_t size = CODE_WIRE[code] == 1 ? 8 : 4;
    if (e - *p < size) return 0;
    const uint8_t *q = *p;
    *p = q + size;
    switch (code) {
    case CODE_F64:
    case CODE_U64:
    case CODE_I64: raw = load64(q); *cell = (int64_t)raw; break; /* a double's bits as they are */
    case CODE_F32: {
        uint32_t bits = load32(q);
        float f;
        double d;
        memcpy(&f, &bits, 4);
        d = (double)f;
        memcpy(cell, &d, 8);
        break;
    }
    case CODE_U32: *cell = (int64_t)load32(q); break;
    default: *cell = (int64_t)(int32_t)load32(q); break; /* CODE_I32 */
    }
    return 1;
}

/* Element `slot` of sequence s is written where it is wanted. */
static inline void put(job *b, Py_ssize_t s, int64_t cell) {
    int64_t slot = b->count[s]++;
    const int64_t *seq = b->seqs + 2 * s;
    if (slot < seq[1]) {
        int64_t col = b->slots[seq[0] + slot];
        if (col >= 0) b->out[col * b->n + b->row] = cell;
    }
}

/* The records of struct sid in [p, e): 1, or 0 for a message to flag. */
static int walk(job *b, const uint8_t *p, const uint8_t *e, Py_ssize_t sid, int depth) {
    if (depth > MAX_DEPTH) return 0;
    const Py_ssize_t f0 = b->first[sid], f1 = b->last[sid];
    while (p < e) {
        uint64_t tag, length;
        if (!varint(&p, e, &tag)) return 0;
        const int wire = (int)(tag & 7);
        const int64_t number = (int64_t)(tag >> 3);
        const uint8_t *body = p, *end;
        switch (wire) {
        case 0:
            if (!varint(&p, e, &length)) return 0;
            end = p;
            break;
        case 1:
            if (e - p < 8) return 0;
            end = p + 8;
            break;
        case 5:
            if (e - p < 4) return 0;
            end = p + 4;
            break;
        case 2:
            if (!varint(&p, e, &length)) return 0;
            if (length > (uint64_t)(e - p)) return 0;
            body = p;
            end = p + length;
            break;
        default: return 0;
        }
        p = end;
        for (Py_ssize_t f = f0; f < f1; f++) {
            const int64_t *row = b->fields + 5 * f;
            if (row[1] != number) continue;
            const int kind = (int)row[2], code = (int)row[3];
            if (kind == 1 ? wire != 2 : wire != CODE_WIRE[code] && (kind == 0 || wire != 2))
                break; /* another wire type than the field's: an unknown field to protobuf */
            if (kind == 1) {
                if (b->seen[row[4]]) return 0;
                b->seen[row[4]] = 1;
                if (!walk(b, body, end, (Py_ssize_t)row[4], depth + 1)) return 0;
            } else if (kind == 0) {
                int64_t cell;
                const uint8_t *q = body;
                if (!item(code, &q, end, &cell) || q != end) return 0;
                b->out[row[4] * b->n + b->row] = cell;
            } else if (wire == 2) { /* a packed run */
                const uint8_t *q = body;
                if (CODE_WIRE[code] != 0 && (end - body) % (CODE_WIRE[code] == 1 ? 8 : 4)) return 0;
                while (q < end) {
                    int64_t cell;
                    if (!item(code, &q, end, &cell)) return 0;
                    put(b, (Py_ssize_t)row[4], cell);
                }
            } else {
                int64_t cell;
                const uint8_t *q = body;
                if (!item(code, &q, end, &cell) || q != end) return 0;
                put(b, (Py_ssize_t)row[4], cell);
            }
            break;
        }
    }
    return 1;
}

static Py_ssize_t run(job *b) {
    Py_ssize_t flagged = 0;
    for (Py_ssize_t i = 0; i < b->n; i++) {
        const int64_t s = b->starts[i], n = b->lengths[i];
        int ok = s >= 0 && n >= 0 && s <= b->len && n <= b->len - s;
        if (ok) {
            memset(b->seen, 0, sizeof(b->seen));
            memset(b->count, 0, sizeof(b->count));
            b->row = i;
            ok = walk(b, b->buf + s, b->buf + s + n, 0, 0);
            for (Py_ssize_t q = 0; ok && q < b->n_seqs; q++)
                if (b->count[q] < b->seqs[2 * q + 1]) ok = 0; /* fewer elements than mapped */
        }
        b->flags[i] = !ok;
        flagged += !ok;
    }
    return flagged;
}

/* scan(buf, starts, lengths, fields, seqs, slots, out, flags) -> flagged
 *
 * buf: the chunk (bytes-like); starts, lengths: int64 per message; fields, seqs, slots: the
 * plan (int64, see the top of this file); out: writable int64, n_columns x n, zeroed (float
 * columns get their doubles' bits); flags: writable uint8 per message, set to 1 for a message
 * left to the numpy path, else 0. Returns how many were flagged. */
static PyObject *scan(PyObject *self, PyObject *args) {
    Py_buffer v[8];
    memset(v, 0, sizeof(v));
    if (!PyArg_ParseTuple(args, "y*y*y*y*y*y*w*w*", &v[0], &v[1], &v[2], &v[3], &v[4], &v[5],
                          &v[6], &v[7]))
        return NULL;
    PyObject *result = NULL;
    job *b = PyMem_Calloc(1, sizeof(job));
    if (b == NULL) {
        PyErr_NoMemory();
        goto done;
    }
    b->buf = v[0].buf;
    b->len = v[0].len;
    b->starts = v[1].buf;
    b->lengths = v[2].buf;
    b->n = v[7].len;
    b->fields = v[3].buf;
    b->n_fields = v[3].len / 40;
    b->seqs = v[4].buf;
    b->n_seqs = v[4].len / 16;
    b->slots = v[5].buf;
    const Py_ssize_t n_slots = v[5].len / 8;
    b->out = v[6].buf;
    b->flags = v[7].buf;
    if (v[1].len / 8 < b->n || v[2].len / 8 < b->n || v[3].len % 40 || v[4].len % 16 ||
        b->n_fields > MAX_FIELDS || b->n_seqs > MAX_SEQS) {
        PyErr_SetString(PyExc_ValueError, "scan: inconsistent sizes");
        goto done;
    }
    if (b->n == 0) {
        result = PyLong_FromSsize_t(0);
        goto done;
    }
    b->n_columns = v[6].len / 8 / b->n;
    /* the plan checked once: every index within its array, structs sorted */
    for (Py_ssize_t s = 0; s < MAX_STRUCTS; s++) b->first[s] = b->last[s] = 0;
    for (Py_ssize_t f = 0; f < b->n_fields; f++) {
        const int64_t *row = b->fields + 5 * f;
        int64_t sid = row[0], kind = row[2], code = row[3], arg = row[4];
        int good = sid >= 0 && sid < MAX_STRUCTS && code >= 0 && code < N_CODES &&
                   (f == 0 || sid >= b->fields[5 * (f - 1)]) &&
                   ((kind == 0 && arg >= 0 && arg < b->n_columns) ||
                    (kind == 1 && arg > 0 && arg < MAX_STRUCTS) ||
                    (kind == 2 && arg >= 0 && arg < b->n_seqs));
        if (!good) {
            PyErr_SetString(PyExc_ValueError, "scan: a field of the plan is out of range");
            goto done;
        }
        if (f == 0 || sid != b->fields[5 * (f - 1)]) b->first[sid] = f;
        b->last[sid] = f + 1;
    }
    for (Py_ssize_t q = 0; q < b->n_seqs; q++) {
        const int64_t first = b->seqs[2 * q], width = b->seqs[2 * q + 1];
        if (first < 0 || width < 0 || width > n_slots - first) {
            PyErr_SetString(PyExc_ValueError, "scan: a sequence of the plan is out of range");
            goto done;
        }
        for (int64_t k = 0; k < width; k++) {
            if (b->slots[first + k] < -1 || b->slots[first + k] >= b->n_columns) {
                PyErr_SetString(PyExc_ValueError, "scan: a slot of the plan is out of range");
                goto done;
            }
        }
    }
    Py_ssize_t flagged;
    Py_BEGIN_ALLOW_THREADS /* the buffers are held: other threads may run meanwhile */
    flagged = run(b);
    Py_END_ALLOW_THREADS
    result = PyLong_FromSsize_t(flagged);
done:
    PyMem_Free(b);
    for (int i = 0; i < 8; i++) PyBuffer_Release(&v[i]);
    return result;
}

static PyMethodDef methods[] = {
    {"scan", scan, METH_VARARGS,
     "scan(buf, starts, lengths, fields, seqs, slots, out, flags) -> flagged: protobuf "
     "messages walked once each and their mapped fields written into out."},
    {NULL, NULL, 0, NULL},
};

static struct PyModuleDef module = {
    PyModuleDef_HEAD_INIT, "_protoscan",
    "Protobuf messages' mapped fields decoded, compiled (imupipe.readers.message_fields).",
    -1, methods,
};

PyMODINIT_FUNC PyInit__protoscan(void) { return PyModule_Create(&module); }
