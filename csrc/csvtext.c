/* jaxshadow._io._csvc: comma-separated numeric tables at array speed.

   A small CPython extension (C99, Python headers only: buffers through the buffer protocol, no
   NumPy headers) used by jaxshadow/_io/meshio.py when it is built; without it the Python routes
   there do the same work.

   - check_rows(body, ncols): the number of rows of `body` when every row ends in '\n' and has
     exactly `ncols` comma-separated fields, with no '"', no '\r' and no blank line; else -1.
   - parse(body, ncols, cols, out): the fields of the columns `cols` of every row into the
     float64 buffer `out` (row-major, len(cols) per row). Each field is optional spaces/tabs, then
     a decimal number (sign, digits, '.', exponent) read by strtod (or, with at most 15 digits
     and a power of ten up to 1e22, by one exact-operand multiply or divide: Clinger's fast
     path, the same correctly rounded value), or inf / infinity / nan (any
     case, with a sign), then optional spaces/tabs: the numbers np.loadtxt reads, to the same
     bits (strtod and Python's parser both round correctly; nan is the quiet NaN with the
     field's sign, as np.loadtxt gives it). Anything else (hex, nan(...), an empty field,
     a field count that changes) returns False, and the caller's Python route reads the table
     and names the bad row. strtod follows the C locale's decimal point: under a locale whose
     decimal point is not "." parse declines (returns False). The GIL is released while parsing.
   - format(values, kinds, lead): text rows for the float64 buffer `values` (row-major,
     len(kinds) per row): for each row, the row's line of `lead` (a buffer of '\n'-ended lines,
     or None) and a comma, then the values joined by commas, then '\n'. kinds[j] is 'g' ("%.9g")
     or 'r' (repr: the shortest text that reads back to the same float64), each formatted by
     PyOS_double_to_string exactly as Python's `"%.9g" % x` and `"%r" % x` do, so the text is
     Python's own. A value equal (bit for bit) to the one above it is copied, not formatted.
*/

#define PY_SSIZE_T_CLEAN
#include <Python.h>

#include <float.h>
#include <locale.h>
#include <math.h>
#include <stdint.h>
#include <stdlib.h>
#include <string.h>

static int is_blank(char c) { return c == ' ' || c == '\t'; }
static int is_digit(char c) { return c >= '0' && c <= '9'; }

static int ieq(const char *s, const char *word, Py_ssize_t n) {
    for (Py_ssize_t i = 0; i < n; i++) {
        char c = s[i];
        if (c >= 'A' && c <= 'Z') c = (char)(c - 'A' + 'a');
        if (c != word[i]) return 0;
    }
    return 1;
}

/* One field [p, e) (e at its ',' or '\n') into *out; 0 when it is a number np.loadtxt reads. */
static int parse_field(const char *p, const char *e, double *out) {
    while (p < e && is_blank(*p)) p++;
    while (e > p && is_blank(e[-1])) e--;
    if (p == e) return -1;
    const char *s = p;
    int neg = 0;
    if (*s == '+' || *s == '-') {
        neg = *s == '-';
        s++;
    }
    Py_ssize_t len = e - s;
    if (len > 0 && !is_digit(*s) && *s != '.') {
        if (len == 3 && ieq(s, "nan", 3)) {
            uint64_t bits = UINT64_C(0x7ff8000000000000) | (neg ? UINT64_C(1) << 63 : 0); /* a quiet NaN */
            memcpy(out, &bits, sizeof bits);
            return 0;
        }
        if ((len == 3 && ieq(s, "inf", 3)) || (len == 8 && ieq(s, "infinity", 8))) {
            *out = neg ? -HUGE_VAL : HUGE_VAL;
            return 0;
        }
        return -1;
    }
    const char *q = s;
    int nd = 0, nfrac = 0;
    uint64_t m = 0; /* the digits as an integer, while there are at most 15 of them */
    while (q < e && is_digit(*q)) m = m * 10 + (uint64_t)(*q++ - '0'), nd++;
    if (q < e && *q == '.') {
        q++;
        while (q < e && is_digit(*q)) m = m * 10 + (uint64_t)(*q++ - '0'), nd++, nfrac++;
    }
    if (nd == 0) return -1;
    int exp = 0, exp_digits = 0, exp_neg = 0;
    if (q < e && (*q == 'e' || *q == 'E')) {
        q++;
        if (q < e && (*q == '+' || *q == '-')) exp_neg = *q++ == '-';
        const char *d = q;
        while (q < e && is_digit(*q)) {
            if (exp_digits < 6) exp = exp * 10 + (*q - '0');
            q++, exp_digits++;
        }
        if (q == d) return -1;
    }
    if (q != e) return -1;
    /* Clinger's fast path: at most 15 digits (an integer below 2^53, exact in a double) and a
       power of ten up to 1e22 (exact too): one IEEE multiply or divide rounds correctly, the
       value strtod gives. */
    int e10 = (exp_neg ? -exp : exp) - nfrac;
    if (FLT_EVAL_METHOD == 0 && nd <= 15 && exp_digits < 6 && e10 >= -22 && e10 <= 22) {
        static const double pow10[23] = {1e0,  1e1,  1e2,  1e3,  1e4,  1e5,  1e6,  1e7,  1e8,  1e9,  1e10, 1e11,
                                         1e12, 1e13, 1e14, 1e15, 1e16, 1e17, 1e18, 1e19, 1e20, 1e21, 1e22};
        double v = (double)m;
        v = e10 >= 0 ? v * pow10[e10] : v / pow10[-e10];
        *out = neg ? -v : v;
        return 0;
    }
    char *end = NULL;
    double v = strtod(p, &end); /* stops at e: the next character is a blank, ',' or '\n' */
    if (end != e) return -1;
    *out = v;
    return 0;
}

static PyObject *check_rows(PyObject *self, PyObject *args) {
    Py_buffer body;
    Py_ssize_t ncols;
    (void)self;
    if (!PyArg_ParseTuple(args, "y*n", &body, &ncols)) return NULL;
    const char *b = (const char *)body.buf, *end = b + body.len;
    Py_ssize_t rows = 0;
    Py_BEGIN_ALLOW_THREADS
    Py_ssize_t commas = 0;
    const char *line = b;
    for (const char *c = b; c < end; c++) {
        char ch = *c;
        if (ch == ',') {
            commas++;
        } else if (ch == '\n') {
            if (c == line || commas != ncols - 1) {
                rows = -1;
                break;
            }
            rows++;
            commas = 0;
            line = c + 1;
        } else if (ch == '"' || ch == '\r') {
            rows = -1;
            break;
        }
    }
    if (rows >= 0 && line != end) rows = -1; /* a last row without its '\n' */
    Py_END_ALLOW_THREADS
    PyBuffer_Release(&body);
    return PyLong_FromSsize_t(rows);
}

static PyObject *parse(PyObject *self, PyObject *args) {
    Py_buffer body, out;
    Py_ssize_t ncols;
    PyObject *cols;
    (void)self;
    if (!PyArg_ParseTuple(args, "y*nOw*", &body, &ncols, &cols, &out)) return NULL;
    Py_ssize_t *where = NULL;
    PyObject *seq = NULL;
    int ok = 0;
    struct lconv *lc = localeconv();
    if (ncols <= 0 || out.len % (Py_ssize_t)sizeof(double) != 0 ||
        lc == NULL || lc->decimal_point == NULL || strcmp(lc->decimal_point, ".") != 0)
        goto done; /* not a float64 buffer, or a locale whose strtod does not read '.' */
    seq = PySequence_Fast(cols, "parse: cols must be a sequence of column indices");
    if (seq == NULL) goto fail;
    Py_ssize_t k = PySequence_Fast_GET_SIZE(seq);
    where = PyMem_Malloc((size_t)ncols * sizeof(Py_ssize_t));
    if (where == NULL) {
        PyErr_NoMemory();
        goto fail;
    }
    for (Py_ssize_t j = 0; j < ncols; j++) where[j] = -1;
    for (Py_ssize_t i = 0; i < k; i++) {
        Py_ssize_t j = PyLong_AsSsize_t(PySequence_Fast_GET_ITEM(seq, i));
        if (j == -1 && PyErr_Occurred()) goto fail;
        if (j < 0 || j >= ncols || where[j] >= 0) {
            PyErr_SetString(PyExc_ValueError, "parse: cols must be distinct indices below ncols");
            goto fail;
        }
        where[j] = i;
    }
    Py_ssize_t cap = out.len / (Py_ssize_t)sizeof(double);
    Py_BEGIN_ALLOW_THREADS
    const char *c = (const char *)body.buf, *end = c + body.len;
    double *o = (double *)out.buf;
    Py_ssize_t filled = 0;
    ok = body.len == 0 || end[-1] == '\n';
    while (ok && c < end) { /* one row: ncols fields, the last ended by '\n' */
        if (filled + k > cap) {
            ok = 0;
            break;
        }
        for (Py_ssize_t j = 0; j < ncols; j++) {
            const char *f = c;
            while (c < end && *c != ',' && *c != '\n') c++;
            if (c == end || (*c == '\n') != (j == ncols - 1)) {
                ok = 0;
                break;
            }
            if (where[j] >= 0 && parse_field(f, c, o + filled + where[j]) != 0) {
                ok = 0;
                break;
            }
            c++;
        }
        filled += k;
    }
    if (filled != cap) ok = 0;
    Py_END_ALLOW_THREADS
    goto done;
fail:
    Py_XDECREF(seq);
    PyMem_Free(where);
    PyBuffer_Release(&body);
    PyBuffer_Release(&out);
    return NULL;
done:
    Py_XDECREF(seq);
    PyMem_Free(where);
    PyBuffer_Release(&body);
    PyBuffer_Release(&out);
    return PyBool_FromLong(ok);
}

#define FIELD_MAX 40 /* repr of a float64 is at most 24 characters, "%.9g" at most 16 */

static PyObject *format(PyObject *self, PyObject *args) {
    Py_buffer values, kinds, lead = {0};
    PyObject *lead_obj;
    (void)self;
    if (!PyArg_ParseTuple(args, "y*y*O", &values, &kinds, &lead_obj)) return NULL;
    PyObject *result = NULL;
    char *prev = NULL;
    uint64_t *prev_bits = NULL;
    int *prev_len = NULL;
    if (lead_obj != Py_None && PyObject_GetBuffer(lead_obj, &lead, PyBUF_SIMPLE) != 0) goto out;
    Py_ssize_t k = kinds.len;
    const char *kind = (const char *)kinds.buf;
    if (k <= 0 || values.len % ((Py_ssize_t)sizeof(double) * k) != 0) {
        PyErr_SetString(PyExc_ValueError, "format: values must be float64 rows of len(kinds) values");
        goto out;
    }
    for (Py_ssize_t j = 0; j < k; j++) {
        if (kind[j] != 'g' && kind[j] != 'r') {
            PyErr_SetString(PyExc_ValueError, "format: kinds must be 'g' or 'r' per column");
            goto out;
        }
    }
    Py_ssize_t n = values.len / ((Py_ssize_t)sizeof(double) * k);
    Py_ssize_t lead_len = lead_obj == Py_None ? 0 : lead.len;
    const char *lc = lead_obj == Py_None ? NULL : (const char *)lead.buf, *lend = lc + lead_len;
    if (n > (PY_SSIZE_T_MAX - lead_len) / (k * (FIELD_MAX + 1) + 2)) {
        PyErr_NoMemory();
        goto out;
    }
    result = PyBytes_FromStringAndSize(NULL, lead_len + n * (k * (FIELD_MAX + 1) + 2));
    prev = PyMem_Malloc((size_t)k * FIELD_MAX);
    prev_bits = PyMem_Malloc((size_t)k * sizeof(uint64_t));
    prev_len = PyMem_Malloc((size_t)k * sizeof(int));
    if (result == NULL || prev == NULL || prev_bits == NULL || prev_len == NULL) {
        if (!PyErr_Occurred()) PyErr_NoMemory();
        Py_CLEAR(result);
        goto out;
    }
    for (Py_ssize_t j = 0; j < k; j++) prev_len[j] = -1;
    char *w = PyBytes_AS_STRING(result);
    const double *v = (const double *)values.buf;
    for (Py_ssize_t i = 0; i < n; i++) {
        if (lc != NULL) {
            const char *nl = lc < lend ? memchr(lc, '\n', (size_t)(lend - lc)) : NULL;
            if (nl == NULL) {
                PyErr_Format(PyExc_ValueError, "format: lead has fewer than %zd lines", n);
                Py_CLEAR(result);
                goto out;
            }
            memcpy(w, lc, (size_t)(nl - lc));
            w += nl - lc;
            *w++ = ',';
            lc = nl + 1;
        }
        for (Py_ssize_t j = 0; j < k; j++) {
            double x = v[i * k + j];
            uint64_t bits;
            memcpy(&bits, &x, sizeof bits);
            if (prev_len[j] < 0 || bits != prev_bits[j]) {
                char *s = kind[j] == 'g' ? PyOS_double_to_string(x, 'g', 9, 0, NULL)
                                         : PyOS_double_to_string(x, 'r', 0, Py_DTSF_ADD_DOT_0, NULL);
                if (s == NULL) {
                    Py_CLEAR(result);
                    goto out;
                }
                size_t len = strlen(s);
                if (len > FIELD_MAX) { /* cannot happen for a double; kept as a guard */
                    PyMem_Free(s);
                    PyErr_SetString(PyExc_ValueError, "format: a value's text is too long");
                    Py_CLEAR(result);
                    goto out;
                }
                memcpy(prev + j * FIELD_MAX, s, len);
                PyMem_Free(s);
                prev_len[j] = (int)len;
                prev_bits[j] = bits;
            }
            memcpy(w, prev + j * FIELD_MAX, (size_t)prev_len[j]);
            w += prev_len[j];
            *w++ = j + 1 < k ? ',' : '\n';
        }
    }
    if (_PyBytes_Resize(&result, w - PyBytes_AS_STRING(result)) != 0) result = NULL;
out:
    PyMem_Free(prev);
    PyMem_Free(prev_bits);
    PyMem_Free(prev_len);
    if (lead_obj != Py_None && lead.obj != NULL) PyBuffer_Release(&lead);
    PyBuffer_Release(&values);
    PyBuffer_Release(&kinds);
    return result;
}

static PyMethodDef methods[] = {
    {"check_rows", check_rows, METH_VARARGS,
     "check_rows(body, ncols) -> rows, or -1 unless every row has ncols fields (no quote, CR, blank line)."},
    {"parse", parse, METH_VARARGS,
     "parse(body, ncols, cols, out) -> bool: columns cols of every row into the float64 buffer out."},
    {"format", format, METH_VARARGS,
     "format(values, kinds, lead) -> bytes: float64 rows as text ('g': %.9g, 'r': repr), after lead's lines."},
    {NULL, NULL, 0, NULL},
};

static struct PyModuleDef module = {PyModuleDef_HEAD_INIT, "_csvc", "CSV tables of numbers at array speed.", -1,
                                    methods, NULL, NULL, NULL, NULL};

PyMODINIT_FUNC PyInit__csvc(void) { return PyModule_Create(&module); }
