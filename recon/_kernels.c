/*
 * teachpath's compiled kernels: the loops of the scan model that numpy can only do with large
 * temporaries or a Python loop. Each has a pure-numpy reference in recon/kernels.py, and the
 * tests compare the two (bit for bit where the arithmetic is the same, see each function).
 *
 * Conventions
 * - Every array arrives through the buffer protocol as a C-contiguous block; recon/kernels.py
 *   makes it so and passes the shapes. Each function checks that every buffer holds exactly the
 *   bytes its shape says (a caller's mistake raises ValueError, never reads past a buffer).
 * - The GIL is released while a kernel runs, so recon/kernels.py can run parts of one call on
 *   several threads.
 * - Compiled with -ffp-contract=off (setup.py): no fused multiply-add, so a product followed by
 *   a sum rounds twice exactly as numpy's separate ufuncs do.
 */
#define PY_SSIZE_T_CLEAN
#include <Python.h>

#include <math.h>
#include <stdint.h>
#include <stdlib.h>
#include <string.h>

/* A buffer of `count` items of `item` bytes, or a ValueError naming it. */
static int expect_size(const Py_buffer *view, Py_ssize_t count, Py_ssize_t item, const char *name)
{
    if (count < 0 || (item > 0 && count > PY_SSIZE_T_MAX / item) || view->len != count * item) {
        PyErr_Format(PyExc_ValueError, "%s holds %zd bytes, its shape says %zd", name, view->len,
                     count >= 0 && count <= PY_SSIZE_T_MAX / (item > 0 ? item : 1) ? count * item
                                                                                   : (Py_ssize_t)-1);
        return -1;
    }
    return 0;
}

/* ---------------------------------------------------------------------------------------- */
/* Nearest points within a radius, on a uniform grid                                          */
/* ---------------------------------------------------------------------------------------- */

typedef struct {
    double d2;
    int64_t index;
} Candidate;

/* Order of candidates: nearer first, the smaller original index first among equals. */
static inline int worse(const Candidate *a, const Candidate *b)
{
    return a->d2 > b->d2 || (a->d2 == b->d2 && a->index > b->index);
}

/* Max-heap on `worse`: heap[0] is the worst of the kept candidates. */
static void sift_down(Candidate *heap, Py_ssize_t size, Py_ssize_t at)
{
    for (;;) {
        Py_ssize_t left = 2 * at + 1, right = left + 1, top = at;
        if (left < size && worse(&heap[left], &heap[top])) top = left;
        if (right < size && worse(&heap[right], &heap[top])) top = right;
        if (top == at) return;
        Candidate swap = heap[at];
        heap[at] = heap[top];
        heap[top] = swap;
        at = top;
    }
}

static void sift_up(Candidate *heap, Py_ssize_t at)
{
    while (at > 0) {
        Py_ssize_t parent = (at - 1) / 2;
        if (!worse(&heap[at], &heap[parent])) return;
        Candidate swap = heap[at];
        heap[at] = heap[parent];
        heap[parent] = swap;
        at = parent;
    }
}

static int by_distance(const void *a, const void *b)
{
    const Candidate *x = a, *y = b;
    return worse(x, y) ? 1 : (worse(y, x) ? -1 : 0);
}

/* First position in sorted `keys[0:n]` whose key is >= `key`. */
static Py_ssize_t lower_bound(const int64_t *keys, Py_ssize_t n, int64_t key)
{
    Py_ssize_t lo = 0, hi = n;
    while (lo < hi) {
        Py_ssize_t mid = lo + (hi - lo) / 2;
        if (keys[mid] < key) lo = mid + 1; else hi = mid;
    }
    return lo;
}

/* The grid cell of one coordinate, clamped to [-1, dim] so that far or non-finite queries
 * cannot overflow the conversion (they find no cell). */
static int64_t cell_of(double value, double origin, double cell, int64_t dim)
{
    double c = floor((value - origin) / cell);
    if (!(c >= -1.0)) return -1; /* also NaN */
    if (c > (double)dim) return dim;
    return (int64_t)c;
}

/* Distance along one axis from a coordinate to the slab of cell `index` (0 inside it). */
static inline double gap_to_cell(double value, double origin, double cell, int64_t index)
{
    double lo = origin + (double)index * cell, hi = lo + cell;
    return value < lo ? lo - value : (value > hi ? value - hi : 0.0);
}

/* A grid of points and the state of a search in it: the candidates of the last query's cell
 * (coordinates apart, so the distance loop vectorises) and room for the hits. */
typedef struct {
    /* The grid (read-only, from the caller's buffers). */
    const double *points, *origin;
    const int64_t *order, *keys, *starts, *dims;
    Py_ssize_t n, u;
    double cell, r2, reach2;
    int64_t span;
    /* The candidates of the cell last searched from. */
    int64_t last_cx, last_cy, last_cz;
    Py_ssize_t capacity, n_candidates;
    double *cand_x, *cand_y, *cand_z, *cand_d2;
    int64_t *cand_index;
    Candidate *hits;
} Search;

static void search_free(Search *s)
{
    free(s->cand_x);
    free(s->cand_y);
    free(s->cand_z);
    free(s->cand_d2);
    free(s->cand_index);
    free(s->hits);
}

/* Room for `needed` candidates; 0 when memory ran out. */
static int search_reserve(Search *s, Py_ssize_t needed)
{
    if (needed <= s->capacity) return 1;
    Py_ssize_t capacity = s->capacity > 0 ? s->capacity : 1024;
    while (capacity < needed) capacity *= 2;
    double *x = realloc(s->cand_x, (size_t)capacity * sizeof(double));
    if (x) s->cand_x = x;
    double *y = realloc(s->cand_y, (size_t)capacity * sizeof(double));
    if (y) s->cand_y = y;
    double *z = realloc(s->cand_z, (size_t)capacity * sizeof(double));
    if (z) s->cand_z = z;
    double *d2 = realloc(s->cand_d2, (size_t)capacity * sizeof(double));
    if (d2) s->cand_d2 = d2;
    int64_t *index = realloc(s->cand_index, (size_t)capacity * sizeof(int64_t));
    if (index) s->cand_index = index;
    Candidate *hits = realloc(s->hits, (size_t)capacity * sizeof(Candidate));
    if (hits) s->hits = hits;
    if (!x || !y || !z || !d2 || !index || !hits) return 0;
    s->capacity = capacity;
    return 1;
}

/* Gather the points of the cells within reach of cell (cx, cy, cz); 0 when memory ran out. */
static int search_gather(Search *s, int64_t cx, int64_t cy, int64_t cz)
{
    const int64_t *dim = s->dims;
    int64_t span = s->span, side = 2 * span + 1;
    int64_t x0 = cx - span < 0 ? 0 : cx - span;
    int64_t x1 = cx + span >= dim[0] ? dim[0] - 1 : cx + span;
    s->n_candidates = 0;
    s->last_cx = cx, s->last_cy = cy, s->last_cz = cz;
    for (int64_t r = 0; r < side * side && x0 <= x1; r++) {
        int64_t iy = cy - span + r % side, iz = cz - span + r / side;
        if (iy < 0 || iy >= dim[1] || iz < 0 || iz >= dim[2]) continue;
        /* Rows farther across y and z than the reach from every point of the cell. */
        double gy = (double)(llabs(iy - cy) > 0 ? llabs(iy - cy) - 1 : 0) * s->cell;
        double gz = (double)(llabs(iz - cz) > 0 ? llabs(iz - cz) - 1 : 0) * s->cell;
        if (gy * gy + gz * gz >= s->reach2) continue;
        /* One row of cells along x is one run of consecutive keys. */
        int64_t row = dim[0] * (iy + dim[1] * iz);
        Py_ssize_t c0 = lower_bound(s->keys, s->u, row + x0);
        Py_ssize_t c1 = lower_bound(s->keys, s->u, row + x1 + 1);
        if (c0 >= c1) continue;
        int64_t j0 = s->starts[c0], j1 = s->starts[c1];
        if (!search_reserve(s, s->n_candidates + (Py_ssize_t)(j1 - j0))) return 0;
        for (int64_t j = j0; j < j1; j++, s->n_candidates++) {
            s->cand_x[s->n_candidates] = s->points[3 * j];
            s->cand_y[s->n_candidates] = s->points[3 * j + 1];
            s->cand_z[s->n_candidates] = s->points[3 * j + 2];
            s->cand_index[s->n_candidates] = s->order[j];
        }
    }
    return 1;
}

/* The k nearest points strictly within the radius of (x, y, z), nearest first (ties by the
 * smaller index), into s->hits; returns how many, or -1 when memory ran out. */
static Py_ssize_t search_query(Search *s, double x, double y, double z, Py_ssize_t k)
{
    if (!(isfinite(x) && isfinite(y) && isfinite(z))) return 0;
    int64_t cx = cell_of(x, s->origin[0], s->cell, s->dims[0]);
    int64_t cy = cell_of(y, s->origin[1], s->cell, s->dims[1]);
    int64_t cz = cell_of(z, s->origin[2], s->cell, s->dims[2]);
    if (cx != s->last_cx || cy != s->last_cy || cz != s->last_cz) {
        if (!search_gather(s, cx, cy, cz)) return -1;
    }
    Py_ssize_t count = s->n_candidates, found = 0;
    const double *px = s->cand_x, *py = s->cand_y, *pz = s->cand_z;
    double *d2 = s->cand_d2;
    for (Py_ssize_t j = 0; j < count; j++) {
        double dx = px[j] - x, dy = py[j] - y, dz = pz[j] - z;
        d2[j] = dx * dx + dy * dy + dz * dz;
    }
    Candidate *hits = s->hits;
    /* Without a branch: every candidate is written at the end of the hits, which grow only by
     * those within the radius (a quarter or so, in no order a branch predictor could learn). */
    const double r2 = s->r2;
    for (Py_ssize_t j = 0; j < count; j++) {
        hits[found].d2 = d2[j];
        hits[found].index = s->cand_index[j];
        found += d2[j] < r2;
    }
    if (found > k) {
        /* The k best of the hits: a max-heap of k over them. */
        for (Py_ssize_t m = 0; m < k; m++) sift_up(hits, m);
        for (Py_ssize_t m = k; m < found; m++) {
            if (worse(&hits[0], &hits[m])) {
                hits[0] = hits[m];
                sift_down(hits, k, 0);
            }
        }
        found = k;
    }
    if (found > 32) {
        qsort(hits, (size_t)found, sizeof(Candidate), by_distance);
    } else {
        for (Py_ssize_t m = 1; m < found; m++) {
            Candidate c = hits[m];
            Py_ssize_t at = m;
            while (at > 0 && worse(&hits[at - 1], &c)) {
                hits[at] = hits[at - 1];
                at--;
            }
            hits[at] = c;
        }
    }
    return found;
}

/* Parses and checks the grid's part of the arguments; 0 with an exception set when they do not
 * fit together. The buffers stay the caller's to release. */
static int search_init(Search *s, Py_buffer *points, Py_buffer *order, Py_buffer *keys,
                       Py_buffer *starts, Py_buffer *origin, double cell, Py_buffer *dims,
                       double radius)
{
    memset(s, 0, sizeof(*s));
    s->n = points->len / (Py_ssize_t)(3 * sizeof(double));
    s->u = keys->len / (Py_ssize_t)sizeof(int64_t);
    if (!(cell > 0.0) || !isfinite(cell) || !(radius >= 0.0) || !isfinite(radius)) {
        PyErr_SetString(PyExc_ValueError, "cell_m must be positive and radius finite, >= 0");
        return 0;
    }
    if (expect_size(points, s->n, 3 * sizeof(double), "points") ||
        expect_size(order, s->n, sizeof(int64_t), "order") ||
        expect_size(starts, s->u + 1, sizeof(int64_t), "cell_starts") ||
        expect_size(origin, 3, sizeof(double), "origin") ||
        expect_size(dims, 3, sizeof(int64_t), "dims"))
        return 0;
    s->points = points->buf, s->order = order->buf, s->keys = keys->buf;
    s->starts = starts->buf, s->origin = origin->buf, s->dims = dims->buf;
    for (int a = 0; a < 3; a++) {
        if (s->dims[a] < 1 || s->dims[a] > (INT64_C(1) << 20)) {
            PyErr_SetString(PyExc_ValueError, "each grid dimension must be in [1, 2**20]");
            return 0;
        }
    }
    /* Every run of points a cell names lies within the points, and the keys increase (checked
     * once here, so the searches cannot read past a buffer). */
    if (s->starts[0] != 0 || s->starts[s->u] != s->n) {
        PyErr_SetString(PyExc_ValueError, "cell_starts must run from 0 to the number of points");
        return 0;
    }
    for (Py_ssize_t c = 0; c < s->u; c++) {
        int64_t key = s->keys[c];
        if (s->starts[c + 1] < s->starts[c] || (c > 0 && key <= s->keys[c - 1]) || key < 0 ||
            key >= s->dims[0] * s->dims[1] * s->dims[2]) {
            PyErr_SetString(PyExc_ValueError,
                            "cell_keys must increase within the grid and cell_starts with them");
            return 0;
        }
    }
    /* Cells are pruned with a slightly larger reach, so that rounding at a cell's boundary
     * never drops a point the exact test (d2 < r2) would keep. */
    double reach = radius * (1.0 + 1e-9) + cell * 1e-9;
    double reach_cells = floor(reach / cell) + 1.0;
    if (!(reach_cells <= 1024.0)) {
        PyErr_SetString(PyExc_ValueError,
                        "the radius spans more than 1024 cells: build the grid with larger cells");
        return 0;
    }
    s->cell = cell, s->r2 = radius * radius, s->reach2 = reach * reach;
    s->span = (int64_t)reach_cells;
    s->last_cx = s->last_cy = s->last_cz = -2;
    return 1;
}

PyDoc_STRVAR(grid_nearest_doc,
"grid_nearest(points, order, cell_keys, cell_starts, origin, cell_m, dims, queries, k, radius,\n"
"             out_distance, out_index, n_points)\n"
"\n"
"For each query, its k nearest points strictly within radius (as scipy's cKDTree.query with\n"
"distance_upper_bound), nearest first, ties by the smaller index; missing ones get distance\n"
"inf and index n_points. points (N, 3) float64 are sorted by cell, order (N,) int64 their\n"
"original indices, cell_keys (U,) int64 the occupied cells' keys ix + dx (iy + dy iz)\n"
"ascending, cell_starts (U + 1,) int64 where each cell's points start; origin (3,) float64,\n"
"dims (3,) int64; queries (Q, 3) float64, fastest in the grid's order; out_distance (Q, k)\n"
"float64, out_index (Q, k) int64.");

static PyObject *grid_nearest(PyObject *self, PyObject *args)
{
    Py_buffer points = {0}, order = {0}, keys = {0}, starts = {0}, origin = {0}, dims = {0};
    Py_buffer queries = {0}, out_distance = {0}, out_index = {0};
    double cell, radius;
    Py_ssize_t k, n_points;
    PyObject *result = NULL;
    Search s;
    memset(&s, 0, sizeof(s));
    if (!PyArg_ParseTuple(args, "y*y*y*y*y*dy*y*ndw*w*n", &points, &order, &keys, &starts,
                          &origin, &cell, &dims, &queries, &k, &radius, &out_distance,
                          &out_index, &n_points))
        return NULL;
    Py_ssize_t q = queries.len / (Py_ssize_t)(3 * sizeof(double));
    if (k < 1 || (q > 0 && k > PY_SSIZE_T_MAX / 8 / q)) {
        PyErr_SetString(PyExc_ValueError, "k must be at least 1 and k x queries addressable");
        goto done;
    }
    if (!search_init(&s, &points, &order, &keys, &starts, &origin, cell, &dims, radius) ||
        expect_size(&queries, q, 3 * sizeof(double), "queries") ||
        expect_size(&out_distance, q * k, sizeof(double), "out_distance") ||
        expect_size(&out_index, q * k, sizeof(int64_t), "out_index"))
        goto done;
    const double *qs = queries.buf;
    double *distance = out_distance.buf;
    int64_t *index = out_index.buf;
    int out_of_memory = 0;
    Py_BEGIN_ALLOW_THREADS
    for (Py_ssize_t i = 0; i < q; i++) {
        Py_ssize_t found = search_query(&s, qs[3 * i], qs[3 * i + 1], qs[3 * i + 2], k);
        if (found < 0) {
            out_of_memory = 1;
            break;
        }
        for (Py_ssize_t m = 0; m < k; m++) {
            distance[i * k + m] = m < found ? sqrt(s.hits[m].d2) : INFINITY;
            index[i * k + m] = m < found ? s.hits[m].index : n_points;
        }
    }
    Py_END_ALLOW_THREADS
    if (out_of_memory) {
        PyErr_NoMemory();
        goto done;
    }
    result = Py_NewRef(Py_None);
done:
    search_free(&s);
    PyBuffer_Release(&points);
    PyBuffer_Release(&order);
    PyBuffer_Release(&keys);
    PyBuffer_Release(&starts);
    PyBuffer_Release(&origin);
    PyBuffer_Release(&dims);
    PyBuffer_Release(&queries);
    PyBuffer_Release(&out_distance);
    PyBuffer_Release(&out_index);
    return result;
}

PyDoc_STRVAR(grid_ball_sums_doc,
"grid_ball_sums(points, order, cell_keys, cell_starts, origin, cell_m, dims, queries, k, radius,\n"
"               columns, n_columns, out_sums, out_counts)\n"
"\n"
"For each query, the sum of columns[j] over its ball: the points j that grid_nearest returns\n"
"for it, added in that order (nearest first) from zero, as the CSR product of\n"
"recon.features.neighbour_balls' matrix with the columns sums them. The grid arguments as for\n"
"grid_nearest; columns (N, C) float64 in the points' original order; out_sums (Q, C) float64,\n"
"out_counts (Q,) int64 the balls' sizes.");

static PyObject *grid_ball_sums(PyObject *self, PyObject *args)
{
    Py_buffer points = {0}, order = {0}, keys = {0}, starts = {0}, origin = {0}, dims = {0};
    Py_buffer queries = {0}, columns = {0}, out_sums = {0}, out_counts = {0};
    double cell, radius;
    Py_ssize_t k, c;
    PyObject *result = NULL;
    Search s;
    memset(&s, 0, sizeof(s));
    if (!PyArg_ParseTuple(args, "y*y*y*y*y*dy*y*ndy*nw*w*", &points, &order, &keys, &starts,
                          &origin, &cell, &dims, &queries, &k, &radius, &columns, &c, &out_sums,
                          &out_counts))
        return NULL;
    Py_ssize_t q = queries.len / (Py_ssize_t)(3 * sizeof(double));
    if (k < 1 || c < 1 || c > 64 || (q > 0 && c > PY_SSIZE_T_MAX / 8 / q)) {
        PyErr_SetString(PyExc_ValueError, "k must be at least 1 and n_columns in [1, 64]");
        goto done;
    }
    if (!search_init(&s, &points, &order, &keys, &starts, &origin, cell, &dims, radius) ||
        expect_size(&queries, q, 3 * sizeof(double), "queries") ||
        expect_size(&columns, s.n, c * sizeof(double), "columns") ||
        expect_size(&out_sums, q, c * sizeof(double), "out_sums") ||
        expect_size(&out_counts, q, sizeof(int64_t), "out_counts"))
        goto done;
    /* The order array maps grid positions to original indices; each must be a valid row of
     * the columns. */
    for (Py_ssize_t j = 0; j < s.n; j++) {
        if (s.order[j] < 0 || s.order[j] >= s.n) {
            PyErr_SetString(PyExc_ValueError, "order must hold indices of the points");
            goto done;
        }
    }
    const double *qs = queries.buf, *col = columns.buf;
    double *sums = out_sums.buf;
    int64_t *counts = out_counts.buf;
    int out_of_memory = 0;
    Py_BEGIN_ALLOW_THREADS
    for (Py_ssize_t i = 0; i < q; i++) {
        Py_ssize_t found = search_query(&s, qs[3 * i], qs[3 * i + 1], qs[3 * i + 2], k);
        if (found < 0) {
            out_of_memory = 1;
            break;
        }
        double *row = sums + i * c;
        for (Py_ssize_t a = 0; a < c; a++) row[a] = 0.0;
        for (Py_ssize_t m = 0; m < found; m++) {
            const double *v = col + s.hits[m].index * c;
            for (Py_ssize_t a = 0; a < c; a++) row[a] += v[a];
        }
        counts[i] = found;
    }
    Py_END_ALLOW_THREADS
    if (out_of_memory) {
        PyErr_NoMemory();
        goto done;
    }
    result = Py_NewRef(Py_None);
done:
    search_free(&s);
    PyBuffer_Release(&points);
    PyBuffer_Release(&order);
    PyBuffer_Release(&keys);
    PyBuffer_Release(&starts);
    PyBuffer_Release(&origin);
    PyBuffer_Release(&dims);
    PyBuffer_Release(&queries);
    PyBuffer_Release(&columns);
    PyBuffer_Release(&out_sums);
    PyBuffer_Release(&out_counts);
    return result;
}

/* ---------------------------------------------------------------------------------------- */
/* Row sums of a 0/1 sparse matrix times dense columns                                         */
/* ---------------------------------------------------------------------------------------- */

PyDoc_STRVAR(csr_row_sums_doc,
"csr_row_sums(indptr, indices, columns, n_columns, out)\n"
"\n"
"out[i] = sum of columns[j] over the column indices j of row i of a CSR matrix of ones, in\n"
"their stored order, from zero: scipy's CSR product with a dense matrix, to the bit. indptr\n"
"(R + 1,) int64, indices (nnz,) int32, columns (M, C) float64, out (R, C) float64.");

static PyObject *csr_row_sums(PyObject *self, PyObject *args)
{
    Py_buffer indptr = {0}, indices = {0}, columns = {0}, out = {0};
    Py_ssize_t c;
    PyObject *result = NULL;
    if (!PyArg_ParseTuple(args, "y*y*y*nw*", &indptr, &indices, &columns, &c, &out)) return NULL;
    Py_ssize_t rows = indptr.len / (Py_ssize_t)sizeof(int64_t) - 1;
    Py_ssize_t nnz = indices.len / (Py_ssize_t)sizeof(int32_t);
    if (c < 1 || c > (1 << 20) || rows < 0) {
        PyErr_SetString(PyExc_ValueError,
                        "n_columns must be in [1, 2**20] and indptr non-empty");
        goto done;
    }
    Py_ssize_t m = columns.len / (Py_ssize_t)(c * sizeof(double));
    if (expect_size(&indptr, rows + 1, sizeof(int64_t), "indptr") ||
        expect_size(&indices, nnz, sizeof(int32_t), "indices") ||
        expect_size(&columns, m, c * sizeof(double), "columns") ||
        expect_size(&out, rows, c * sizeof(double), "out"))
        goto done;
    const int64_t *ptr = indptr.buf;
    const int32_t *idx = indices.buf;
    const double *col = columns.buf;
    double *sums = out.buf;
    int bad = 0;
    Py_BEGIN_ALLOW_THREADS
    for (Py_ssize_t i = 0; i < rows && !bad; i++) {
        double *row = sums + i * c;
        for (Py_ssize_t a = 0; a < c; a++) row[a] = 0.0;
        int64_t j0 = ptr[i], j1 = ptr[i + 1];
        if (j0 < 0 || j1 > nnz || j0 > j1) { bad = 1; break; }
        for (int64_t jj = j0; jj < j1; jj++) {
            int32_t j = idx[jj];
            if (j < 0 || j >= m) { bad = 1; break; }
            const double *v = col + (Py_ssize_t)j * c;
            for (Py_ssize_t a = 0; a < c; a++) row[a] += v[a];
        }
    }
    Py_END_ALLOW_THREADS
    if (bad) {
        PyErr_SetString(PyExc_ValueError, "indptr or indices out of range");
        goto done;
    }
    result = Py_NewRef(Py_None);
done:
    PyBuffer_Release(&indptr);
    PyBuffer_Release(&indices);
    PyBuffer_Release(&columns);
    PyBuffer_Release(&out);
    return result;
}

/* ---------------------------------------------------------------------------------------- */
/* The slices' Hough votes                                                                    */
/* ---------------------------------------------------------------------------------------- */

PyDoc_STRVAR(hough_votes_doc,
"hough_votes(x, y, phi, weight, b, k, cos_theta, sin_theta, step, half_window, radius_m,\n"
"            rho_bin_m, n_rho, out)\n"
"\n"
"recon.profiles' Hough accumulator: each weighted point (x, y, phi (B, K) float64, weight\n"
"(B, K) uint8) votes in its normal's direction bin (phi / step) and half_window bins either\n"
"side, shared linearly between the two nearest offset bins. cos_theta, sin_theta (T,) float64\n"
"are the bins' directions; out (B, T, n_rho) float64. The same arithmetic in the same order\n"
"as the numpy reference (two bincounts, added), so the result is the same to the bit.");

static PyObject *hough_votes(PyObject *self, PyObject *args)
{
    Py_buffer xs = {0}, ys = {0}, phis = {0}, weights = {0}, cos_t = {0}, sin_t = {0}, out = {0};
    Py_ssize_t b, k, half_window, n_rho;
    double step, radius, bin;
    PyObject *result = NULL;
    double *upper = NULL;
    if (!PyArg_ParseTuple(args, "y*y*y*y*nny*y*dnddnw*", &xs, &ys, &phis, &weights, &b, &k,
                          &cos_t, &sin_t, &step, &half_window, &radius, &bin, &n_rho, &out))
        return NULL;
    Py_ssize_t t = cos_t.len / (Py_ssize_t)sizeof(double);
    if (b < 0 || k < 0 || t < 1 || n_rho < 2 || half_window < 0 || !(step > 0.0) ||
        !(bin > 0.0)) {
        PyErr_SetString(PyExc_ValueError, "bad Hough grid: need B, K >= 0, T >= 1, n_rho >= 2");
        goto done;
    }
    if (b > 0 && k > PY_SSIZE_T_MAX / b) {
        PyErr_SetString(PyExc_ValueError, "B x K is too large");
        goto done;
    }
    if (n_rho > PY_SSIZE_T_MAX / t ||
        (b > 0 && t * n_rho > PY_SSIZE_T_MAX / (Py_ssize_t)sizeof(double) / b)) {
        PyErr_SetString(PyExc_ValueError, "B x T x n_rho is too large");
        goto done;
    }
    if (expect_size(&xs, b * k, sizeof(double), "x") ||
        expect_size(&ys, b * k, sizeof(double), "y") ||
        expect_size(&phis, b * k, sizeof(double), "phi") ||
        expect_size(&weights, b * k, 1, "weight") ||
        expect_size(&cos_t, t, sizeof(double), "cos_theta") ||
        expect_size(&sin_t, t, sizeof(double), "sin_theta") ||
        expect_size(&out, b * t * n_rho, sizeof(double), "out"))
        goto done;
    Py_ssize_t size = b * t * n_rho;
    upper = calloc(size > 0 ? (size_t)size : 1, sizeof(double));
    if (upper == NULL) {
        PyErr_NoMemory();
        goto done;
    }
    const double *x = xs.buf, *y = ys.buf, *phi = phis.buf, *ct = cos_t.buf, *st = sin_t.buf;
    const uint8_t *w = weights.buf;
    double *lower = out.buf;
    Py_BEGIN_ALLOW_THREADS
    memset(lower, 0, (size_t)size * sizeof(double));
    for (Py_ssize_t s = 0; s < b; s++) {
        for (Py_ssize_t j = 0; j < k; j++) {
            Py_ssize_t at = s * k + j;
            if (!w[at]) continue; /* adds zeros in the reference */
            double centre_f = floor(phi[at] / step);
            /* phi lies in [0, pi): the bin is small; anything else is clamped, never indexed
             * out of range. */
            int64_t centre = isfinite(centre_f) ? (int64_t)fmax(fmin(centre_f, 1e6), -1e6) : 0;
            for (Py_ssize_t d = -half_window; d <= half_window; d++) {
                int64_t tb = (centre + d) % (int64_t)t;
                if (tb < 0) tb += t;
                double rho = x[at] * ct[tb] + y[at] * st[tb];
                double position = ((rho + radius) + bin) / bin - 0.5;
                double low_f = floor(position);
                double frac = position - low_f;
                int64_t low;
                if (!(low_f >= 0.0)) low = 0; /* also NaN */
                else if (low_f > (double)(n_rho - 2)) low = n_rho - 2;
                else low = (int64_t)low_f;
                Py_ssize_t flat = (s * t + tb) * n_rho + low;
                lower[flat] += 1.0 - frac;
                upper[flat + 1] += frac;
            }
        }
    }
    for (Py_ssize_t i = 0; i < size; i++) lower[i] += upper[i];
    Py_END_ALLOW_THREADS
    result = Py_NewRef(Py_None);
done:
    free(upper);
    PyBuffer_Release(&xs);
    PyBuffer_Release(&ys);
    PyBuffer_Release(&phis);
    PyBuffer_Release(&weights);
    PyBuffer_Release(&cos_t);
    PyBuffer_Release(&sin_t);
    PyBuffer_Release(&out);
    return result;
}

/* ---------------------------------------------------------------------------------------- */
/* One real point per voxel                                                                   */
/* ---------------------------------------------------------------------------------------- */

PyDoc_STRVAR(voxel_nearest_centre_doc,
"voxel_nearest_centre(points, origin, scale, dims, out_kept) -> (kept, resolution2)\n"
"\n"
"Of the points (N, 3) float64 in each voxel, keeps the one nearest the voxel's centre (the\n"
"smaller index among equals) into out_kept (N,) int64, in the order of the voxels' keys, and\n"
"returns how many voxels hold points and the largest squared distance (m^2) of a point from\n"
"the point kept for its voxel. A point's voxel is the integer part c of (p - origin) * scale\n"
"(origin (3,)), its key (c0 * dims1 + c1) * dims2 + c2 (dims (3,) int64, each voxel count at\n"
"least 1, their product below 2^62); every point must lie in that grid. Its distance from the\n"
"centre is measured in voxel units, as recon.kernels' reference does, so the two pick the\n"
"same points. The voxels are found by hashing their keys (no sort of the points).");

typedef struct {
    int64_t key; /* -1: empty */
    int64_t best;
    double to_centre;
} VoxelSlot;

static int by_voxel_key(const void *a, const void *b)
{
    const VoxelSlot *x = a, *y = b;
    return (x->key > y->key) - (x->key < y->key);
}

/* The voxel key of point i, and its distance from the voxel's centre (voxel units, squared);
 * -1 for a point outside the grid (or not finite). */
static inline int64_t voxel_key(const double *p, const double *o, double scale, const int64_t *dims,
                                double *to_centre)
{
    int64_t c[3];
    double f[3];
    for (int a = 0; a < 3; a++) {
        double rel = (p[a] - o[a]) * scale;
        if (!(rel >= 0.0) || !(rel < (double)dims[a])) return -1;
        c[a] = (int64_t)rel;
        f[a] = (rel - (double)c[a]) - 0.5;
    }
    *to_centre = f[0] * f[0] + f[1] * f[1] + f[2] * f[2];
    return (c[0] * dims[1] + c[1]) * dims[2] + c[2];
}

/* The slot of `key` in the open-addressed table (mask + 1 slots, a power of two): its own,
 * or the empty one where it belongs. */
static inline Py_ssize_t voxel_slot(const VoxelSlot *table, size_t mask, int64_t key)
{
    size_t h = ((uint64_t)key * UINT64_C(0x9E3779B97F4A7C15)) >> 20;
    for (;; h++) {
        const VoxelSlot *slot = &table[h & mask];
        if (slot->key == key || slot->key < 0) return (Py_ssize_t)(h & mask);
    }
}

/* The table's slots moved into one twice as large (capacity doubles; NULL, the old table kept,
 * when memory runs out). */
static VoxelSlot *wider_voxel_table(VoxelSlot *table, size_t capacity)
{
    VoxelSlot *wider = PyMem_RawMalloc(2 * capacity * sizeof(VoxelSlot));
    if (wider == NULL) return NULL;
    size_t wider_mask = 2 * capacity - 1;
    for (size_t h = 0; h < 2 * capacity; h++) wider[h].key = -1;
    for (size_t h = 0; h < capacity; h++)
        if (table[h].key >= 0) wider[voxel_slot(wider, wider_mask, table[h].key)] = table[h];
    PyMem_RawFree(table);
    return wider;
}

static PyObject *voxel_nearest_centre(PyObject *self, PyObject *args)
{
    Py_buffer points = {0}, origin = {0}, dims_view = {0}, out_kept = {0};
    double scale;
    PyObject *result = NULL;
    VoxelSlot *table = NULL;
    if (!PyArg_ParseTuple(args, "y*y*dy*w*", &points, &origin, &scale, &dims_view, &out_kept))
        return NULL;
    Py_ssize_t n = points.len / (Py_ssize_t)(3 * sizeof(double));
    if (expect_size(&points, n, 3 * sizeof(double), "points") ||
        expect_size(&origin, 3, sizeof(double), "origin") ||
        expect_size(&dims_view, 3, sizeof(int64_t), "dims") ||
        expect_size(&out_kept, n, sizeof(int64_t), "out_kept"))
        goto done;
    if (!(scale > 0.0) || !isfinite(scale)) {
        PyErr_SetString(PyExc_ValueError, "scale must be positive and finite");
        goto done;
    }
    const int64_t *dims = dims_view.buf;
    double voxels = 1.0;
    for (int a = 0; a < 3; a++) {
        if (dims[a] < 1) {
            PyErr_SetString(PyExc_ValueError, "dims must be at least 1 voxel along each axis");
            goto done;
        }
        voxels *= (double)dims[a];
    }
    if (voxels >= 4611686018427387904.0) { /* 2^62: keys must fit, with room to spare */
        PyErr_SetString(PyExc_ValueError, "dims hold too many voxels (2^62 or more)");
        goto done;
    }
    /* The table grows with the voxels found (kept at most half full): a scan thinned tenfold
     * keeps it a tenth of the points' size, and its random reads in cache. */
    size_t capacity = 1024;
    table = PyMem_RawMalloc(capacity * sizeof(VoxelSlot));
    if (table == NULL) {
        PyErr_NoMemory();
        goto done;
    }
    const double *p = points.buf, *o = origin.buf;
    int64_t *kept = out_kept.buf;
    size_t mask = capacity - 1;
    Py_ssize_t groups = 0, outside = -1;
    int out_of_memory = 0;
    double worst2 = 0.0;
    Py_BEGIN_ALLOW_THREADS
    for (size_t h = 0; h < capacity; h++) table[h].key = -1;
    /* Points in index order: a strictly smaller distance wins, so among equals the smaller
     * index stays (as the reference's stable sort keeps it). */
    for (Py_ssize_t i = 0; i < n; i++) {
        double to_centre;
        int64_t key = voxel_key(&p[3 * i], o, scale, dims, &to_centre);
        if (key < 0) {
            outside = i;
            break;
        }
        VoxelSlot *slot = &table[voxel_slot(table, mask, key)];
        if (slot->key < 0) {
            slot->key = key;
            slot->best = i;
            slot->to_centre = to_centre;
            if (2 * (size_t)++groups > capacity) { /* kept at most half full */
                VoxelSlot *wider = wider_voxel_table(table, capacity);
                if (wider == NULL) {
                    out_of_memory = 1;
                    break;
                }
                table = wider;
                capacity *= 2;
                mask = capacity - 1;
            }
        } else if (to_centre < slot->to_centre) {
            slot->best = i;
            slot->to_centre = to_centre;
        }
    }
    if (outside < 0 && !out_of_memory) {
        for (Py_ssize_t i = 0; i < n; i++) {
            double to_centre;
            int64_t key = voxel_key(&p[3 * i], o, scale, dims, &to_centre);
            int64_t best = table[voxel_slot(table, mask, key)].best;
            double d[3];
            for (int a = 0; a < 3; a++) d[a] = p[3 * i + a] - p[3 * best + a];
            double d2 = d[0] * d[0] + d[1] * d[1] + d[2] * d[2];
            if (d2 > worst2) worst2 = d2;
        }
        /* The voxels in the order of their keys. */
        Py_ssize_t used = 0;
        for (size_t h = 0; h < capacity; h++)
            if (table[h].key >= 0) table[used++] = table[h];
        qsort(table, (size_t)used, sizeof(VoxelSlot), by_voxel_key);
        for (Py_ssize_t g = 0; g < used; g++) kept[g] = table[g].best;
    }
    Py_END_ALLOW_THREADS
    if (out_of_memory) {
        PyErr_NoMemory();
        goto done;
    }
    if (outside >= 0) {
        PyErr_Format(PyExc_ValueError,
                     "point %zd lies outside the voxel grid (below the origin, beyond dims, or "
                     "not finite)",
                     outside);
        goto done;
    }
    result = Py_BuildValue("nd", groups, worst2);
done:
    PyMem_RawFree(table);
    PyBuffer_Release(&points);
    PyBuffer_Release(&origin);
    PyBuffer_Release(&dims_view);
    PyBuffer_Release(&out_kept);
    return result;
}

/* ---------------------------------------------------------------------------------------- */
/* Rows gathered by index, padding as zeros                                                   */
/* ---------------------------------------------------------------------------------------- */

PyDoc_STRVAR(gather_rows_doc,
"gather_rows(values, m, c, index, fill, out)\n"
"\n"
"out[i] = values[index[i]] for each of the N indices (int64), zeros where index[i] == fill:\n"
"values (m, c) and out (N, c) float64. An index outside [0, m) other than fill is a\n"
"ValueError (nothing is read past values). Copies only, so the result is the reference's to\n"
"the bit.");

static PyObject *gather_rows(PyObject *self, PyObject *args)
{
    Py_buffer values = {0}, index = {0}, out = {0};
    Py_ssize_t m, c;
    long long fill;
    PyObject *result = NULL;
    if (!PyArg_ParseTuple(args, "y*nny*Lw*", &values, &m, &c, &index, &fill, &out)) return NULL;
    if (m < 0 || c < 1 || c > (1 << 20)) {
        PyErr_SetString(PyExc_ValueError, "m must be >= 0 and c in [1, 2**20]");
        goto done;
    }
    Py_ssize_t n = index.len / (Py_ssize_t)sizeof(int64_t);
    if (expect_size(&values, m, c * (Py_ssize_t)sizeof(double), "values") ||
        expect_size(&index, n, sizeof(int64_t), "index") ||
        expect_size(&out, n, c * (Py_ssize_t)sizeof(double), "out"))
        goto done;
    const double *src = values.buf;
    const int64_t *at = index.buf;
    double *dst = out.buf;
    Py_ssize_t bad = -1;
    Py_BEGIN_ALLOW_THREADS
    for (Py_ssize_t i = 0; i < n; i++) {
        int64_t j = at[i];
        double *row = dst + i * c;
        if (j == fill) {
            memset(row, 0, (size_t)c * sizeof(double));
        } else if (j < 0 || j >= m) {
            bad = i;
            break;
        } else {
            memcpy(row, src + (Py_ssize_t)j * c, (size_t)c * sizeof(double));
        }
    }
    Py_END_ALLOW_THREADS
    if (bad >= 0) {
        PyErr_Format(PyExc_ValueError, "index %lld (entry %zd) is outside [0, %zd)",
                     (long long)at[bad], bad, m);
        goto done;
    }
    result = Py_NewRef(Py_None);
done:
    PyBuffer_Release(&values);
    PyBuffer_Release(&index);
    PyBuffer_Release(&out);
    return result;
}

/* ---------------------------------------------------------------------------------------- */
/* Weighted moments of batches of 3-D neighbourhoods                                          */
/* ---------------------------------------------------------------------------------------- */

PyDoc_STRVAR(weighted_moments_doc,
"weighted_moments(points, weights, b, k, out_total, out_mean, out_cov)\n"
"\n"
"For each of b neighbourhoods of k points (points (b, k, 3), weights (b, k), float64): the\n"
"total weight, the weighted mean (sum w p / total; total 1 where it is not positive) and the\n"
"weighted covariance about that mean (sum w (p - mean)(p - mean)^T / the same), into\n"
"out_total (b,), out_mean (b, 3), out_cov (b, 3, 3). The reference (recon.fitting's numpy\n"
"weighted_pca) sums through BLAS in its own order: the two agree to rounding, not to the bit.");

static PyObject *weighted_moments(PyObject *self, PyObject *args)
{
    Py_buffer points = {0}, weights = {0}, out_total = {0}, out_mean = {0}, out_cov = {0};
    Py_ssize_t b, k;
    PyObject *result = NULL;
    if (!PyArg_ParseTuple(args, "y*y*nnw*w*w*", &points, &weights, &b, &k, &out_total,
                          &out_mean, &out_cov))
        return NULL;
    if (b < 0 || k < 0 || (b > 0 && k > PY_SSIZE_T_MAX / 24 / b)) {
        PyErr_SetString(PyExc_ValueError, "b and k must be >= 0 (and b * k * 3 floats fit)");
        goto done;
    }
    if (expect_size(&points, b * k, 3 * sizeof(double), "points") ||
        expect_size(&weights, b * k, sizeof(double), "weights") ||
        expect_size(&out_total, b, sizeof(double), "out_total") ||
        expect_size(&out_mean, b, 3 * sizeof(double), "out_mean") ||
        expect_size(&out_cov, b, 9 * sizeof(double), "out_cov"))
        goto done;
    const double *p = points.buf, *w = weights.buf;
    double *total = out_total.buf, *mean = out_mean.buf, *cov = out_cov.buf;
    Py_BEGIN_ALLOW_THREADS
    for (Py_ssize_t i = 0; i < b; i++) {
        const double *pi = p + i * k * 3, *wi = w + i * k;
        double t = 0.0, m[3] = {0.0, 0.0, 0.0};
        for (Py_ssize_t j = 0; j < k; j++) {
            t += wi[j];
            m[0] += wi[j] * pi[3 * j];
            m[1] += wi[j] * pi[3 * j + 1];
            m[2] += wi[j] * pi[3 * j + 2];
        }
        double safe = t > 0.0 ? t : 1.0;
        for (int a = 0; a < 3; a++) m[a] /= safe;
        double c00 = 0, c01 = 0, c02 = 0, c11 = 0, c12 = 0, c22 = 0;
        for (Py_ssize_t j = 0; j < k; j++) {
            double d0 = pi[3 * j] - m[0], d1 = pi[3 * j + 1] - m[1], d2 = pi[3 * j + 2] - m[2];
            double w0 = wi[j] * d0, w1 = wi[j] * d1, w2 = wi[j] * d2;
            c00 += w0 * d0;
            c01 += w0 * d1;
            c02 += w0 * d2;
            c11 += w1 * d1;
            c12 += w1 * d2;
            c22 += w2 * d2;
        }
        total[i] = t;
        for (int a = 0; a < 3; a++) mean[3 * i + a] = m[a];
        double *ci = cov + 9 * i;
        ci[0] = c00 / safe;
        ci[1] = ci[3] = c01 / safe;
        ci[2] = ci[6] = c02 / safe;
        ci[4] = c11 / safe;
        ci[5] = ci[7] = c12 / safe;
        ci[8] = c22 / safe;
    }
    Py_END_ALLOW_THREADS
    result = Py_NewRef(Py_None);
done:
    PyBuffer_Release(&points);
    PyBuffer_Release(&weights);
    PyBuffer_Release(&out_total);
    PyBuffer_Release(&out_mean);
    PyBuffer_Release(&out_cov);
    return result;
}

/* ---------------------------------------------------------------------------------------- */
/* Weighted least squares in batches of neighbourhoods                                        */
/* ---------------------------------------------------------------------------------------- */

/* Shapes of a batch of least-squares problems, checked against the buffers. */
static int expect_least_squares(const Py_buffer *design, const Py_buffer *y,
                                const Py_buffer *weights, Py_ssize_t b, Py_ssize_t k,
                                Py_ssize_t p, Py_ssize_t m)
{
    if (b < 0 || k < 0 || p < 1 || p > 64 || m < 1 || m > 64 ||
        (b > 0 && k > PY_SSIZE_T_MAX / 8 / 64 / b)) {
        PyErr_SetString(PyExc_ValueError,
                        "b and k must be >= 0, p and m in [1, 64] (and b * k * 64 floats fit)");
        return -1;
    }
    if (expect_size(design, b * k, p * (Py_ssize_t)sizeof(double), "design") ||
        expect_size(y, b * k, m * (Py_ssize_t)sizeof(double), "y") ||
        expect_size(weights, b * k, sizeof(double), "weights"))
        return -1;
    return 0;
}

PyDoc_STRVAR(normal_equations_doc,
"normal_equations(design, y, weights, b, k, p, m, out_normal, out_rhs)\n"
"\n"
"For each of b problems of k rows (design (b, k, p), y (b, k, m), weights (b, k), float64):\n"
"out_normal (b, p, p) = A^T W A and out_rhs (b, p, m) = A^T W y, summed over the rows in\n"
"order (p and m at most 64). The reference (recon.fitting's numpy fit_linear) multiplies\n"
"through BLAS in its own order: the two agree to rounding, not to the bit.");

static PyObject *normal_equations(PyObject *self, PyObject *args)
{
    Py_buffer design = {0}, y = {0}, weights = {0}, out_normal = {0}, out_rhs = {0};
    Py_ssize_t b, k, p, m;
    PyObject *result = NULL;
    if (!PyArg_ParseTuple(args, "y*y*y*nnnnw*w*", &design, &y, &weights, &b, &k, &p, &m,
                          &out_normal, &out_rhs))
        return NULL;
    if (expect_least_squares(&design, &y, &weights, b, k, p, m) ||
        expect_size(&out_normal, b, p * p * (Py_ssize_t)sizeof(double), "out_normal") ||
        expect_size(&out_rhs, b, p * m * (Py_ssize_t)sizeof(double), "out_rhs"))
        goto done;
    const double *a = design.buf, *yy = y.buf, *w = weights.buf;
    double *normal = out_normal.buf, *rhs = out_rhs.buf;
    Py_BEGIN_ALLOW_THREADS
    for (Py_ssize_t i = 0; i < b; i++) {
        double *ni = normal + i * p * p, *ri = rhs + i * p * m;
        memset(ni, 0, (size_t)(p * p) * sizeof(double));
        memset(ri, 0, (size_t)(p * m) * sizeof(double));
        for (Py_ssize_t j = 0; j < k; j++) {
            Py_ssize_t row = i * k + j;
            double wj = w[row];
            if (wj == 0.0) continue; /* padding adds nothing (a finite row times zero) */
            const double *aj = a + row * p, *yj = yy + row * m;
            for (Py_ssize_t r = 0; r < p; r++) {
                double wa = wj * aj[r];
                for (Py_ssize_t c = r; c < p; c++) ni[r * p + c] += wa * aj[c];
                for (Py_ssize_t c = 0; c < m; c++) ri[r * m + c] += wa * yj[c];
            }
        }
        for (Py_ssize_t r = 0; r < p; r++)
            for (Py_ssize_t c = 0; c < r; c++) ni[r * p + c] = ni[c * p + r];
    }
    Py_END_ALLOW_THREADS
    result = Py_NewRef(Py_None);
done:
    PyBuffer_Release(&design);
    PyBuffer_Release(&y);
    PyBuffer_Release(&weights);
    PyBuffer_Release(&out_normal);
    PyBuffer_Release(&out_rhs);
    return result;
}

PyDoc_STRVAR(residual_squares_doc,
"residual_squares(design, y, weights, coef, b, k, p, m, out)\n"
"\n"
"out (b,) = sum over rows and outputs of w (y - A coef)^2 for each of b problems (design\n"
"(b, k, p), y (b, k, m), weights (b, k), coef (b, p, m), float64). Agrees with the numpy\n"
"reference to rounding.");

static PyObject *residual_squares(PyObject *self, PyObject *args)
{
    Py_buffer design = {0}, y = {0}, weights = {0}, coef = {0}, out = {0};
    Py_ssize_t b, k, p, m;
    PyObject *result = NULL;
    if (!PyArg_ParseTuple(args, "y*y*y*y*nnnnw*", &design, &y, &weights, &coef, &b, &k, &p, &m,
                          &out))
        return NULL;
    if (expect_least_squares(&design, &y, &weights, b, k, p, m) ||
        expect_size(&coef, b, p * m * (Py_ssize_t)sizeof(double), "coef") ||
        expect_size(&out, b, sizeof(double), "out"))
        goto done;
    const double *a = design.buf, *yy = y.buf, *w = weights.buf, *cf = coef.buf;
    double *sq = out.buf;
    Py_BEGIN_ALLOW_THREADS
    for (Py_ssize_t i = 0; i < b; i++) {
        const double *ci = cf + i * p * m;
        double total = 0.0;
        for (Py_ssize_t j = 0; j < k; j++) {
            Py_ssize_t row = i * k + j;
            if (w[row] == 0.0) continue;
            const double *aj = a + row * p, *yj = yy + row * m;
            double part = 0.0;
            for (Py_ssize_t c = 0; c < m; c++) {
                double fitted = 0.0;
                for (Py_ssize_t r = 0; r < p; r++) fitted += aj[r] * ci[r * m + c];
                double e = yj[c] - fitted;
                part += e * e;
            }
            total += w[row] * part;
        }
        sq[i] = total;
    }
    Py_END_ALLOW_THREADS
    result = Py_NewRef(Py_None);
done:
    PyBuffer_Release(&design);
    PyBuffer_Release(&y);
    PyBuffer_Release(&weights);
    PyBuffer_Release(&coef);
    PyBuffer_Release(&out);
    return result;
}

static PyMethodDef methods[] = {
    {"grid_nearest", grid_nearest, METH_VARARGS, grid_nearest_doc},
    {"grid_ball_sums", grid_ball_sums, METH_VARARGS, grid_ball_sums_doc},
    {"csr_row_sums", csr_row_sums, METH_VARARGS, csr_row_sums_doc},
    {"hough_votes", hough_votes, METH_VARARGS, hough_votes_doc},
    {"voxel_nearest_centre", voxel_nearest_centre, METH_VARARGS, voxel_nearest_centre_doc},
    {"gather_rows", gather_rows, METH_VARARGS, gather_rows_doc},
    {"weighted_moments", weighted_moments, METH_VARARGS, weighted_moments_doc},
    {"normal_equations", normal_equations, METH_VARARGS, normal_equations_doc},
    {"residual_squares", residual_squares, METH_VARARGS, residual_squares_doc},
    {NULL, NULL, 0, NULL},
};

static struct PyModuleDef module = {
    PyModuleDef_HEAD_INIT, "recon._kernels",
    "teachpath's compiled kernels (see recon/kernels.py, which is what to import).", -1, methods,
};

PyMODINIT_FUNC PyInit__kernels(void) { return PyModule_Create(&module); }
