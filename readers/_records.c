/*
 * imupipe.readers._records: the sequential record walks of the flight-log readers, compiled.
 *
 * A PX4 ULog's records (https://docs.px4.io/main/en/dev_log/ulog_file_format.html) follow each
 * other without an index: a 3-byte header (uint16 payload size, little-endian; uint8 type), then
 * the payload. Where record k starts is known only after record k-1 is read, so the walk is
 * sequential: numpy cannot do it without a Python step per record. This module does the walk
 * and the copy of fixed-size payloads in C; everything else (which records are what, the
 * structured dtypes, the values) stays in Python and numpy (imupipe.readers.record_walk, which
 * holds the pure-Python equivalents of both functions, tested equal).
 *
 * Only the CPython C API and the buffer protocol are used (no numpy C API): the offsets are
 * returned as bytes of native int64 for numpy.frombuffer.
 */
#define PY_SSIZE_T_CLEAN
#include <Python.h>
#include <stdint.h>
#include <string.h>

/* ulog_walk(buf, start, limit) -> (offsets, sizes, kinds, ids, end)
 *
 * The records that lie whole in buf[start:limit] (limit clipped to len(buf)), walking from
 * start: a record at o is taken when o + 3 + size <= limit; the walk stops at the first record
 * that is not (or when fewer than 3 bytes are left). Per record, as bytes for numpy.frombuffer:
 * its offset (native int64), payload size (native uint16), type (uint8) and the payload's first
 * two bytes as a little-endian uint16 (a data record's msg_id; 0 for a payload shorter than 2).
 * end is where the walk stopped (the end of the last record taken). */
static PyObject *ulog_walk(PyObject *self, PyObject *args) {
    Py_buffer view;
    Py_ssize_t start, limit;
    if (!PyArg_ParseTuple(args, "y*nn", &view, &start, &limit)) return NULL;
    const uint8_t *buf = (const uint8_t *)view.buf;
    Py_ssize_t len = view.len;
    if (limit > len) limit = len;
    if (start < 0) start = 0;
    /* two passes: count the records, then write them into the bytes returned (no buffer sized
     * for the worst case, one record per 3 bytes) */
    Py_ssize_t n = 0, o = start;
    while (o + 3 <= limit) {
        Py_ssize_t size = (Py_ssize_t)buf[o] | ((Py_ssize_t)buf[o + 1] << 8);
        if (o + 3 + size > limit) break;
        n++;
        o += 3 + size;
    }
    Py_ssize_t end = o;
    PyObject *offsets = PyBytes_FromStringAndSize(NULL, n * (Py_ssize_t)sizeof(int64_t));
    PyObject *sizes = PyBytes_FromStringAndSize(NULL, n * (Py_ssize_t)sizeof(uint16_t));
    PyObject *kinds = PyBytes_FromStringAndSize(NULL, n);
    PyObject *ids = PyBytes_FromStringAndSize(NULL, n * (Py_ssize_t)sizeof(uint16_t));
    if (offsets == NULL || sizes == NULL || kinds == NULL || ids == NULL) {
        Py_XDECREF(offsets);
        Py_XDECREF(sizes);
        Py_XDECREF(kinds);
        Py_XDECREF(ids);
        PyBuffer_Release(&view);
        return NULL;
    }
    char *out = PyBytes_AS_STRING(offsets);
    char *out_size = PyBytes_AS_STRING(sizes);
    char *out_kind = PyBytes_AS_STRING(kinds);
    char *out_id = PyBytes_AS_STRING(ids);
    o = start;
    for (Py_ssize_t i = 0; i < n; i++) {
        int64_t at = (int64_t)o;
        uint16_t size = (uint16_t)(buf[o] | (buf[o + 1] << 8));
        uint16_t id = size >= 2 ? (uint16_t)(buf[o + 3] | (buf[o + 4] << 8)) : 0;
        memcpy(out + i * (Py_ssize_t)sizeof(int64_t), &at, sizeof(int64_t));
        memcpy(out_size + i * (Py_ssize_t)sizeof(uint16_t), &size, sizeof(uint16_t));
        out_kind[i] = (char)buf[o + 2];
        memcpy(out_id + i * (Py_ssize_t)sizeof(uint16_t), &id, sizeof(uint16_t));
        o += 3 + (Py_ssize_t)size;
    }
    PyBuffer_Release(&view);
    return Py_BuildValue("NNNNn", offsets, sizes, kinds, ids, end);
}

/* gather(buf, offsets, skip, size) -> bytearray
 *
 * buf[o + skip : o + skip + size] for each int64 o of offsets, concatenated (the fixed-size
 * payloads of one topic's records, for numpy.frombuffer with the topic's dtype; a bytearray, so
 * that the arrays are writable, as pyulog's). */
static PyObject *gather(PyObject *self, PyObject *args) {
    Py_buffer view, offs;
    Py_ssize_t skip, size;
    if (!PyArg_ParseTuple(args, "y*y*nn", &view, &offs, &skip, &size)) return NULL;
    Py_ssize_t n = offs.len / (Py_ssize_t)sizeof(int64_t);
    if (size < 0 || skip < 0) {
        PyBuffer_Release(&view);
        PyBuffer_Release(&offs);
        PyErr_SetString(PyExc_ValueError, "gather: negative size or skip");
        return NULL;
    }
    PyObject *result = PyByteArray_FromStringAndSize(NULL, n * size);
    if (result == NULL) {
        PyBuffer_Release(&view);
        PyBuffer_Release(&offs);
        return NULL;
    }
    char *dst = PyByteArray_AS_STRING(result);
    const char *src = (const char *)view.buf;
    const char *raw = (const char *)offs.buf;
    for (Py_ssize_t i = 0; i < n; i++) {
        int64_t o;
        memcpy(&o, raw + i * (Py_ssize_t)sizeof(int64_t), sizeof(int64_t));
        if (o < 0 || o + skip + size > view.len) {
            PyBuffer_Release(&view);
            PyBuffer_Release(&offs);
            Py_DECREF(result);
            PyErr_Format(PyExc_IndexError, "gather: offset %lld out of the buffer", (long long)o);
            return NULL;
        }
        memcpy(dst + i * size, src + o + skip, (size_t)size);
    }
    PyBuffer_Release(&view);
    PyBuffer_Release(&offs);
    return result;
}

/* dataflash_walk(buf, lengths, first_def) -> offsets: bytes of int64
 *
 * An ArduPilot DataFlash log's records as pymavlink's DFReader walks them: from the start, a
 * record is 0xA3 0x95 <type> at p where the type is known (lengths[type] > 0: its FMT length,
 * header included), defined before p (first_def[type] < p: the offset of its first FMT) and
 * whole (p + lengths[type] <= len(buf)); the next record is searched from its end; any other
 * byte is skipped. lengths and first_def: 256 native int64 each. */
static PyObject *dataflash_walk(PyObject *self, PyObject *args) {
    Py_buffer view, lens, defs;
    if (!PyArg_ParseTuple(args, "y*y*y*", &view, &lens, &defs)) return NULL;
    if (lens.len != 256 * (Py_ssize_t)sizeof(int64_t) ||
        defs.len != 256 * (Py_ssize_t)sizeof(int64_t)) {
        PyBuffer_Release(&view);
        PyBuffer_Release(&lens);
        PyBuffer_Release(&defs);
        PyErr_SetString(PyExc_ValueError, "dataflash_walk: lengths and first_def: 256 int64");
        return NULL;
    }
    const uint8_t *buf = (const uint8_t *)view.buf;
    int64_t length[256], first[256];
    memcpy(length, lens.buf, sizeof(length));
    memcpy(first, defs.buf, sizeof(first));
    PyBuffer_Release(&lens);
    PyBuffer_Release(&defs);
    Py_ssize_t len = view.len;
    PyObject *offsets = NULL;
    for (int pass = 0; pass < 2; pass++) { /* count, then write */
        Py_ssize_t n = 0, p = 0;
        char *out = offsets == NULL ? NULL : PyBytes_AS_STRING(offsets);
        while (p + 2 < len) {
            if (buf[p] == 0xA3 && buf[p + 1] == 0x95) {
                uint8_t t = buf[p + 2];
                int64_t size = length[t];
                if (size > 0 && first[t] < (int64_t)p && (int64_t)p + size <= (int64_t)len) {
                    if (out != NULL) {
                        int64_t at = (int64_t)p;
                        memcpy(out + n * (Py_ssize_t)sizeof(int64_t), &at, sizeof(int64_t));
                    }
                    n++;
                    p += (Py_ssize_t)size;
                    continue;
                }
            }
            p++;
        }
        if (offsets == NULL) {
            offsets = PyBytes_FromStringAndSize(NULL, n * (Py_ssize_t)sizeof(int64_t));
            if (offsets == NULL) {
                PyBuffer_Release(&view);
                return NULL;
            }
        }
    }
    PyBuffer_Release(&view);
    return offsets;
}

/* ulog_formats(buf, offsets, sizes) -> list
 *
 * The ULog format records ('F') whose payloads are buf[o + 3 : o + 3 + size] (offsets and
 * sizes: native int64 each), split as imupipe.readers.ulog.records._format splits them (pyulog's
 * MessageFormat): per record (name, fields), the name the text before the first ':', fields a
 * list of (type, array size or 0, field name) of each non-empty ';'-separated entry of the text
 * between the first and the second ':' (the entry's text up to its first space the type, up to
 * the next space the name; "type[n]" an array of n). Only for a payload of ASCII bytes whose
 * every entry has a space and whose every array size is 1 to 4 decimal digits between the
 * type's first '[' and its first ']'; None for any other record, which the caller splits in
 * Python (where pyulog's own errors come from). */
static PyObject *format_fields(const char *s, Py_ssize_t n) {
    const char *end = s + n;
    for (const char *c = s; c < end; c++)
        if ((unsigned char)*c >= 0x80) Py_RETURN_NONE;
    const char *colon = memchr(s, ':', (size_t)n);
    if (colon == NULL) Py_RETURN_NONE;
    const char *text = colon + 1;
    const char *text_end = memchr(text, ':', (size_t)(end - text));
    if (text_end == NULL) text_end = end;
    PyObject *fields = PyList_New(0);
    if (fields == NULL) return NULL;
    const char *entry = text;
    for (;;) {
        const char *stop = memchr(entry, ';', (size_t)(text_end - entry));
        if (stop == NULL) stop = text_end;
        if (stop > entry) {
            const char *space = memchr(entry, ' ', (size_t)(stop - entry));
            if (space == NULL) {
                Py_DECREF(fields);
                Py_RETURN_NONE;
            }
            const char *name = space + 1;
            const char *name_end = memchr(name, ' ', (size_t)(stop - name));
            if (name_end == NULL) name_end = stop;
            const char *open = memchr(entry, '[', (size_t)(space - entry));
            const char *type_end = space;
            long count = 0;
            if (open != NULL) {
                const char *close = memchr(entry, ']', (size_t)(space - entry));
                Py_ssize_t digits = close == NULL ? 0 : close - open - 1;
                if (digits < 1 || digits > 4) {
                    Py_DECREF(fields);
                    Py_RETURN_NONE;
                }
                for (const char *d = open + 1; d < close; d++) {
                    if (*d < '0' || *d > '9') {
                        Py_DECREF(fields);
                        Py_RETURN_NONE;
                    }
                    count = count * 10 + (*d - '0');
                }
                type_end = open;
            }
            PyObject *field = Py_BuildValue("(s#ls#)", entry, (Py_ssize_t)(type_end - entry),
                                            count, name, (Py_ssize_t)(name_end - name));
            if (field == NULL || PyList_Append(fields, field) < 0) {
                Py_XDECREF(field);
                Py_DECREF(fields);
                return NULL;
            }
            Py_DECREF(field);
        }
        if (stop == text_end) break;
        entry = stop + 1;
    }
    return Py_BuildValue("(s#N)", s, (Py_ssize_t)(colon - s), fields);
}

static PyObject *ulog_formats(PyObject *self, PyObject *args) {
    Py_buffer view, offs, lens;
    if (!PyArg_ParseTuple(args, "y*y*y*", &view, &offs, &lens)) return NULL;
    Py_ssize_t n = offs.len / (Py_ssize_t)sizeof(int64_t);
    PyObject *result = NULL;
    if (lens.len != offs.len) {
        PyErr_SetString(PyExc_ValueError, "ulog_formats: one size per offset");
        goto done;
    }
    result = PyList_New(n);
    if (result == NULL) goto done;
    for (Py_ssize_t i = 0; i < n; i++) {
        int64_t o, size;
        memcpy(&o, (const char *)offs.buf + i * (Py_ssize_t)sizeof(int64_t), sizeof(int64_t));
        memcpy(&size, (const char *)lens.buf + i * (Py_ssize_t)sizeof(int64_t), sizeof(int64_t));
        if (o < 0 || size < 0 || o + 3 + size > view.len) {
            Py_CLEAR(result);
            PyErr_Format(PyExc_IndexError, "ulog_formats: record at %lld out of the buffer",
                         (long long)o);
            goto done;
        }
        PyObject *item = format_fields((const char *)view.buf + o + 3, (Py_ssize_t)size);
        if (item == NULL) {
            Py_CLEAR(result);
            goto done;
        }
        PyList_SET_ITEM(result, i, item);
    }
done:
    PyBuffer_Release(&view);
    PyBuffer_Release(&offs);
    PyBuffer_Release(&lens);
    return result;
}

static PyMethodDef methods[] = {
    {"ulog_walk", ulog_walk, METH_VARARGS,
     "ulog_walk(buf, start, limit) -> (offsets, sizes, kinds, ids, end): the ULog records "
     "lying whole in buf[start:limit]."},
    {"dataflash_walk", dataflash_walk, METH_VARARGS,
     "dataflash_walk(buf, lengths, first_def) -> offsets as int64 bytes: a DataFlash log's "
     "records, as pymavlink's DFReader walks them."},
    {"ulog_formats", ulog_formats, METH_VARARGS,
     "ulog_formats(buf, offsets, sizes) -> [(name, [(type, n, field), ...]) or None]: ULog "
     "format records split, the plain ones."},
    {"gather", gather, METH_VARARGS,
     "gather(buf, offsets, skip, size) -> bytearray: buf[o+skip:o+skip+size] of each int64 offset, "
     "concatenated."},
    {NULL, NULL, 0, NULL},
};

static struct PyModuleDef module = {
    PyModuleDef_HEAD_INIT, "_records",
    "The sequential record walks of the flight-log readers, compiled (imupipe.readers.record_walk).",
    -1, methods,
};

PyMODINIT_FUNC PyInit__records(void) { return PyModule_Create(&module); }
