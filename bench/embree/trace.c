/*
 * trace.c - all-hits line tracing benchmark for native Embree 3.
 *
 * Reads an RLINES1 file (triangles + bundles of parallel lines, see
 * README.md), builds one Embree scene and, for each query mode, finds EVERY
 * crossing of every line with the scene for t in (0, 4).  All-hits tracing is
 * done the usual Embree way: a filter function records each candidate hit in
 * a per-ray buffer and rejects it, so that traversal goes on to the next one.
 * After each ray (or packet of 8 rays) the consumer sorts each line's hits by
 * t and appends them to a per-thread output, as a real user would.
 *
 * Prints one JSON line per mode on stdout; diagnostics go to stderr.
 *
 * Build: cc -O3 -march=native -o trace trace.c -lembree3 -lpthread -lm
 * Run:   ./trace FILE [--threads N] [--repeat R]
 *                     [--mode all|occluded8|occluded1|intersect1]
 *                     [--robust] [--expect CROSSINGS]
 */

#include <embree3/rtcore.h>

#include <errno.h>
#include <math.h>
#include <pthread.h>
#include <stdarg.h>
#include <stdatomic.h>
#include <stdint.h>
#include <stdio.h>
#include <stdlib.h>
#include <string.h>
#include <time.h>

#define TNEAR 0.0f
#define TFAR 4.0f
#define PACKET 8     /* lanes of an RTCRay8 packet = ray slots per thread */
#define HIST_BINS 9  /* lines with 0, 1, ..., 7 and >= 8 crossings */

/* ------------------------------------------------------------------------ */
/* Small helpers                                                              */
/* ------------------------------------------------------------------------ */

static void die(const char *fmt, ...)
{
    va_list ap;
    va_start(ap, fmt);
    fputs("trace: ", stderr);
    vfprintf(stderr, fmt, ap);
    fputc('\n', stderr);
    va_end(ap);
    exit(1);
}

static void *xrealloc(void *p, size_t bytes)
{
    void *q = realloc(p, bytes);
    if (q == NULL && bytes != 0)
        die("out of memory (%zu bytes)", bytes);
    return q;
}

static double now_seconds(void)
{
    struct timespec ts;
    clock_gettime(CLOCK_MONOTONIC, &ts);
    return (double)ts.tv_sec + 1e-9 * (double)ts.tv_nsec;
}

/* 64-bit finaliser (splitmix64): a commutative sum of these over all hits is
 * an order-independent fingerprint of the set of (line, primID) crossings. */
static uint64_t mix64(uint64_t x)
{
    x += 0x9e3779b97f4a7c15ull;
    x = (x ^ (x >> 30)) * 0xbf58476d1ce4e5b9ull;
    x = (x ^ (x >> 27)) * 0x94d049bb133111ebull;
    return x ^ (x >> 31);
}

/* ------------------------------------------------------------------------ */
/* Input file                                                                 */
/* ------------------------------------------------------------------------ */

typedef struct {
    float dir[3];     /* unit direction shared by all lines of the bundle */
    uint32_t count;   /* number of lines */
    size_t first;     /* index of the bundle's first line in Input.origins */
} Bundle;

typedef struct {
    uint32_t tri_count;
    float *tris;          /* tri_count x 9 floats: a.xyz b.xyz c.xyz */
    uint32_t bundle_count;
    Bundle *bundles;
    size_t line_count;
    float *origins;       /* line_count x 3 floats */
} Input;

/* Bounds-checked little-endian reader over the whole file in memory. */
typedef struct {
    const unsigned char *p;
    size_t left;
    const char *path;
} Reader;

static const void *take(Reader *r, size_t bytes, const char *what)
{
    if (bytes > r->left)
        die("%s: bad file: truncated while reading %s", r->path, what);
    const void *p = r->p;
    r->p += bytes;
    r->left -= bytes;
    return p;
}

static uint32_t take_u32(Reader *r, const char *what)
{
    uint32_t v;
    memcpy(&v, take(r, 4, what), 4); /* host is little-endian (checked) */
    return v;
}

static void load_input(const char *path, Input *in)
{
    const uint32_t one = 1;
    if (*(const unsigned char *)&one != 1)
        die("this program assumes a little-endian host");

    FILE *f = fopen(path, "rb");
    if (f == NULL)
        die("%s: %s", path, strerror(errno));
    if (fseek(f, 0, SEEK_END) != 0)
        die("%s: cannot seek", path);
    long size = ftell(f);
    if (size < 0 || fseek(f, 0, SEEK_SET) != 0)
        die("%s: cannot get size", path);
    unsigned char *data = xrealloc(NULL, (size_t)size + 1);
    if (fread(data, 1, (size_t)size, f) != (size_t)size)
        die("%s: read error", path);
    fclose(f);

    Reader r = { data, (size_t)size, path };
    if (memcmp(take(&r, 8, "magic"), "RLINES1\0", 8) != 0)
        die("%s: bad file: magic is not \"RLINES1\\0\"", path);

    in->tri_count = take_u32(&r, "triangle count");
    if (in->tri_count == 0)
        die("%s: bad file: no triangles", path);
    if ((size_t)in->tri_count > r.left / 36)
        die("%s: bad file: %u triangles do not fit in the file", path, in->tri_count);
    size_t tri_bytes = (size_t)in->tri_count * 36;
    in->tris = xrealloc(NULL, tri_bytes);
    memcpy(in->tris, take(&r, tri_bytes, "triangles"), tri_bytes);

    in->bundle_count = take_u32(&r, "bundle count");
    if ((size_t)in->bundle_count > r.left / 16)
        die("%s: bad file: %u bundles do not fit in the file", path, in->bundle_count);
    in->bundles = xrealloc(NULL, (size_t)in->bundle_count * sizeof(Bundle) + 1);

    /* First pass: headers and line count; remember where origins start. */
    Reader origins_at = r;
    in->line_count = 0;
    for (uint32_t b = 0; b < in->bundle_count; b++) {
        Bundle *bu = &in->bundles[b];
        memcpy(bu->dir, take(&r, 12, "bundle direction"), 12);
        bu->count = take_u32(&r, "bundle line count");
        if ((size_t)bu->count > r.left / 12)
            die("%s: bad file: bundle %u claims %u lines past the end", path, b, bu->count);
        take(&r, (size_t)bu->count * 12, "origins");
        bu->first = in->line_count;
        in->line_count += bu->count;

        float len = sqrtf(bu->dir[0] * bu->dir[0] + bu->dir[1] * bu->dir[1] +
                          bu->dir[2] * bu->dir[2]);
        if (!(fabsf(len - 1.0f) < 1e-3f))
            die("%s: bad file: bundle %u direction is not unit (length %g)", path, b,
                (double)len);
    }
    if (r.left != 0)
        die("%s: bad file: %zu trailing bytes", path, r.left);

    /* Second pass: copy the origins into one contiguous array. */
    in->origins = xrealloc(NULL, in->line_count * 12 + 1);
    r = origins_at;
    for (uint32_t b = 0; b < in->bundle_count; b++) {
        Bundle *bu = &in->bundles[b];
        take(&r, 16, "bundle header");
        size_t bytes = (size_t)bu->count * 12;
        memcpy(in->origins + 3 * bu->first, take(&r, bytes, "origins"), bytes);
    }
    free(data);
}

/* ------------------------------------------------------------------------ */
/* Per-thread state, filter function and consumer                            */
/* ------------------------------------------------------------------------ */

typedef struct {
    float t;
    uint32_t prim;
} Crossing;

/* Hits collected for one ray while Embree traverses it. */
typedef struct {
    Crossing *hits;
    uint32_t n, cap;
} Slot;

typedef struct {
    /* Scratch: one slot per ray in flight (8 for packets, 1 otherwise). */
    Slot slot[PACKET];

    /* Output, as a consumer would keep it: per line its crossing count,
     * then all crossings back to back, each line's sorted by t. */
    uint32_t *counts;
    size_t n_counts, cap_counts;
    Crossing *out;
    size_t n_out, cap_out;

    /* Statistics for the current pass. */
    uint64_t filter_calls;   /* invocations of the filter function */
    uint64_t filter_lanes;   /* valid lanes seen over all invocations */
    uint64_t duplicates;     /* same primID reported twice for one ray */
    uint64_t out_of_range;   /* hits with t outside the open (0, 4) */
    uint64_t hist[HIST_BINS];
    uint64_t fingerprint;    /* sum of mix64(line, primID) */
} ThreadState;

/* Embree passes the context pointer we give to rtcOccluded / rtcIntersect
 * unchanged to the filter, so extending it is how the filter finds the
 * calling thread's buffers.  The Embree context must be the first member. */
typedef struct {
    struct RTCIntersectContext ctx;
    ThreadState *ts;
} TraceContext;

/* SOA accessors for RTCRayN / RTCHitN (the rtcore_ray.h helpers are C++-only).
 * Layouts: ray = org_x org_y org_z tnear dir_x dir_y dir_z time tfar mask id
 * flags; hit = Ng_x Ng_y Ng_z u v primID geomID instID, each an array of N. */
static inline float rayn_tfar(const struct RTCRayN *ray, unsigned N, unsigned i)
{
    return ((const float *)ray)[8 * N + i];
}
static inline unsigned rayn_id(const struct RTCRayN *ray, unsigned N, unsigned i)
{
    return ((const unsigned *)ray)[10 * N + i];
}
static inline unsigned hitn_primid(const struct RTCHitN *hit, unsigned N, unsigned i)
{
    return ((const unsigned *)hit)[5 * N + i];
}

/*
 * Filter function for both intersect and occluded queries: record the
 * candidate hit in the ray's slot and reject it so traversal continues.
 *
 * The slot is taken from the ray's id field (set to the packet lane, or 0 for
 * single rays) rather than from the lane index i: that stays correct however
 * Embree chooses to call the filter (N = 1, 4, 8, or a packet with only some
 * lanes valid).  The hit distance is the ray's tfar during the call.
 */
static void record_and_reject(const struct RTCFilterFunctionNArguments *args)
{
    ThreadState *ts = ((const TraceContext *)args->context)->ts;
    const unsigned N = args->N;

    ts->filter_calls++;
    for (unsigned i = 0; i < N; i++) {
        if (args->valid[i] == 0)
            continue;
        args->valid[i] = 0; /* reject: Embree keeps looking for further hits */
        ts->filter_lanes++;

        float t = rayn_tfar(args->ray, N, i);
        /* Lines are the open segment t in (0, 4); Embree's own range test
         * may also let t == tnear or t == tfar through. */
        if (!(t > TNEAR && t < TFAR)) {
            ts->out_of_range++;
            continue;
        }
        unsigned prim = hitn_primid(args->hit, N, i);
        Slot *s = &ts->slot[rayn_id(args->ray, N, i) % PACKET];

        /* Embree documents that a primitive may be reported more than once
         * (spatial splits with RTC_BUILD_QUALITY_HIGH); drop and count those.
         * A line has only a handful of hits, so a linear scan is cheapest. */
        int seen = 0;
        for (uint32_t k = 0; k < s->n; k++)
            if (s->hits[k].prim == prim) {
                seen = 1;
                break;
            }
        if (seen) {
            ts->duplicates++;
            continue;
        }
        if (s->n == s->cap) {
            s->cap = s->cap ? 2 * s->cap : 16;
            s->hits = xrealloc(s->hits, s->cap * sizeof(Crossing));
        }
        s->hits[s->n++] = (Crossing){ t, prim };
    }
}

/* Consumer: sort the line's hits by t and append them to the thread output. */
static void emit_line(ThreadState *ts, Slot *s, size_t line)
{
    /* Insertion sort: a line typically has 0-4 hits. */
    for (uint32_t i = 1; i < s->n; i++) {
        Crossing c = s->hits[i];
        uint32_t j = i;
        for (; j > 0 && s->hits[j - 1].t > c.t; j--)
            s->hits[j] = s->hits[j - 1];
        s->hits[j] = c;
    }

    if (ts->n_counts == ts->cap_counts) {
        ts->cap_counts = ts->cap_counts ? 2 * ts->cap_counts : 4096;
        ts->counts = xrealloc(ts->counts, ts->cap_counts * sizeof(uint32_t));
    }
    ts->counts[ts->n_counts++] = s->n;

    ts->hist[s->n < HIST_BINS - 1 ? s->n : HIST_BINS - 1]++;
    if (s->n == 0)
        return;

    if (ts->n_out + s->n > ts->cap_out) {
        while (ts->n_out + s->n > ts->cap_out)
            ts->cap_out = ts->cap_out ? 2 * ts->cap_out : 16384;
        ts->out = xrealloc(ts->out, ts->cap_out * sizeof(Crossing));
    }
    memcpy(ts->out + ts->n_out, s->hits, s->n * sizeof(Crossing));
    ts->n_out += s->n;

    for (uint32_t k = 0; k < s->n; k++)
        ts->fingerprint += mix64(((uint64_t)line << 32) ^ s->hits[k].prim);
    s->n = 0;
}

/* ------------------------------------------------------------------------ */
/* Tracing modes                                                              */
/* ------------------------------------------------------------------------ */

typedef enum { MODE_OCCLUDED8, MODE_OCCLUDED1, MODE_INTERSECT1, MODE_COUNT } Mode;
static const char *const mode_names[MODE_COUNT] = { "occluded8", "occluded1", "intersect1" };

/* One bundle with rtcOccluded8: packets of 8 parallel lines, tail masked. */
static void trace_bundle_occluded8(RTCScene scene, TraceContext *tc, const Input *in,
                                   const Bundle *b)
{
    struct RTCRay8 ray; /* RTC_ALIGN(32) in the header */
    int valid[PACKET];
    for (uint32_t j = 0; j < b->count; j += PACKET) {
        uint32_t lanes = b->count - j < PACKET ? b->count - j : PACKET;
        for (unsigned k = 0; k < PACKET; k++) {
            /* Inactive lanes repeat the last active line; valid[] masks them. */
            const float *o = in->origins + 3 * (b->first + j + (k < lanes ? k : lanes - 1));
            valid[k] = k < lanes ? -1 : 0;
            ray.org_x[k] = o[0];
            ray.org_y[k] = o[1];
            ray.org_z[k] = o[2];
            ray.tnear[k] = TNEAR;
            ray.dir_x[k] = b->dir[0];
            ray.dir_y[k] = b->dir[1];
            ray.dir_z[k] = b->dir[2];
            ray.time[k] = 0.0f;
            ray.tfar[k] = TFAR;
            ray.mask[k] = 0xFFFFFFFFu;
            ray.id[k] = k; /* slot of this lane, read back by the filter */
            ray.flags[k] = 0;
        }
        rtcOccluded8(valid, scene, &tc->ctx, &ray);
        for (unsigned k = 0; k < lanes; k++)
            emit_line(tc->ts, &tc->ts->slot[k], b->first + j + k);
    }
}

/* Fill a single ray for line `line` of bundle b (slot 0). */
static void init_ray1(struct RTCRay *ray, const Input *in, const Bundle *b, size_t line)
{
    const float *o = in->origins + 3 * line;
    *ray = (struct RTCRay){
        .org_x = o[0], .org_y = o[1], .org_z = o[2], .tnear = TNEAR,
        .dir_x = b->dir[0], .dir_y = b->dir[1], .dir_z = b->dir[2], .time = 0.0f,
        .tfar = TFAR, .mask = 0xFFFFFFFFu, .id = 0, .flags = 0,
    };
}

/* One bundle with rtcOccluded1, one line at a time. */
static void trace_bundle_occluded1(RTCScene scene, TraceContext *tc, const Input *in,
                                   const Bundle *b)
{
    struct RTCRay ray;
    for (size_t line = b->first; line < b->first + b->count; line++) {
        init_ray1(&ray, in, b, line);
        rtcOccluded1(scene, &tc->ctx, &ray);
        emit_line(tc->ts, &tc->ts->slot[0], line);
    }
}

/* One bundle with rtcIntersect1, one line at a time. */
static void trace_bundle_intersect1(RTCScene scene, TraceContext *tc, const Input *in,
                                    const Bundle *b)
{
    struct RTCRayHit rh;
    for (size_t line = b->first; line < b->first + b->count; line++) {
        init_ray1(&rh.ray, in, b, line);
        rh.hit.geomID = RTC_INVALID_GEOMETRY_ID;
        rh.hit.instID[0] = RTC_INVALID_GEOMETRY_ID;
        rtcIntersect1(scene, &tc->ctx, &rh);
        emit_line(tc->ts, &tc->ts->slot[0], line);
    }
}

/* Work shared by the threads of one pass. */
typedef struct {
    RTCScene scene;
    const Input *in;
    Mode mode;
    atomic_uint next_bundle; /* dynamic scheduling: next bundle to take */
} Job;

typedef struct {
    Job *job;
    ThreadState *ts;
} Worker;

static void *worker_main(void *arg)
{
    Worker *w = arg;
    Job *job = w->job;
    TraceContext tc;
    rtcInitIntersectContext(&tc.ctx); /* defaults: incoherent, no context filter */
    tc.ts = w->ts;

    for (;;) {
        unsigned b = atomic_fetch_add_explicit(&job->next_bundle, 1, memory_order_relaxed);
        if (b >= job->in->bundle_count)
            break;
        const Bundle *bu = &job->in->bundles[b];
        switch (job->mode) {
        case MODE_OCCLUDED8:  trace_bundle_occluded8(job->scene, &tc, job->in, bu); break;
        case MODE_OCCLUDED1:  trace_bundle_occluded1(job->scene, &tc, job->in, bu); break;
        case MODE_INTERSECT1: trace_bundle_intersect1(job->scene, &tc, job->in, bu); break;
        default: break;
        }
    }
    return NULL;
}

/* Totals of one pass over all lines. */
typedef struct {
    double seconds;
    uint64_t crossings, lines, filter_calls, filter_lanes, duplicates, out_of_range;
    uint64_t hist[HIST_BINS];
    uint64_t fingerprint;
} PassResult;

static PassResult run_pass(RTCScene scene, const Input *in, Mode mode, int threads,
                           ThreadState **ts)
{
    Job job = { .scene = scene, .in = in, .mode = mode };
    atomic_init(&job.next_bundle, 0);
    Worker *workers = xrealloc(NULL, (size_t)threads * sizeof *workers);
    pthread_t *tids = xrealloc(NULL, (size_t)threads * sizeof *tids);

    for (int i = 0; i < threads; i++) {
        /* Keep allocations from earlier passes; only reset the contents. */
        ThreadState *t = ts[i];
        t->n_counts = t->n_out = 0;
        t->filter_calls = t->filter_lanes = t->duplicates = t->out_of_range = 0;
        memset(t->hist, 0, sizeof t->hist);
        t->fingerprint = 0;
        workers[i] = (Worker){ &job, t };
    }

    double t0 = now_seconds();
    for (int i = 0; i < threads; i++)
        if (pthread_create(&tids[i], NULL, worker_main, &workers[i]) != 0)
            die("pthread_create failed");
    for (int i = 0; i < threads; i++)
        pthread_join(tids[i], NULL);
    PassResult r = { .seconds = now_seconds() - t0 };
    free(workers);
    free(tids);

    for (int i = 0; i < threads; i++) {
        const ThreadState *t = ts[i];
        r.crossings += t->n_out;
        r.lines += t->n_counts;
        r.filter_calls += t->filter_calls;
        r.filter_lanes += t->filter_lanes;
        r.duplicates += t->duplicates;
        r.out_of_range += t->out_of_range;
        for (int k = 0; k < HIST_BINS; k++)
            r.hist[k] += t->hist[k];
        r.fingerprint += t->fingerprint;
    }
    return r;
}

/* ------------------------------------------------------------------------ */
/* Embree setup                                                               */
/* ------------------------------------------------------------------------ */

static atomic_int embree_failed;

static void on_embree_error(void *user, enum RTCError code, const char *msg)
{
    (void)user;
    fprintf(stderr, "trace: embree error %d: %s\n", (int)code, msg ? msg : "(no message)");
    atomic_store(&embree_failed, 1);
}

/* One triangle geometry with its own (copied) vertex and index buffers. */
static RTCScene build_scene(RTCDevice device, const Input *in, int robust, int high)
{
    RTCScene scene = rtcNewScene(device);
    /* --quality high: RTC_BUILD_QUALITY_HIGH (spatial splits, whose repeated
     * reports of one triangle the filter drops). */
    if (high)
        rtcSetSceneBuildQuality(scene, RTC_BUILD_QUALITY_HIGH);
    /* Defaults: RTC_SCENE_FLAG_NONE and RTC_BUILD_QUALITY_MEDIUM.  --robust
     * sets RTC_SCENE_FLAG_ROBUST ("avoid optimizations that reduce arithmetic
     * accuracy"), which changes what lines through edges and vertices get. */
    if (robust)
        rtcSetSceneFlags(scene, RTC_SCENE_FLAG_ROBUST);
    RTCGeometry geom = rtcNewGeometry(device, RTC_GEOMETRY_TYPE_TRIANGLE);

    /* Embree allocates these with the padding its SIMD loads need. */
    float *verts = rtcSetNewGeometryBuffer(geom, RTC_BUFFER_TYPE_VERTEX, 0,
                                           RTC_FORMAT_FLOAT3, 3 * sizeof(float),
                                           3 * (size_t)in->tri_count);
    unsigned *index = rtcSetNewGeometryBuffer(geom, RTC_BUFFER_TYPE_INDEX, 0,
                                              RTC_FORMAT_UINT3, 3 * sizeof(unsigned),
                                              in->tri_count);
    if (verts == NULL || index == NULL)
        die("cannot allocate Embree buffers");
    memcpy(verts, in->tris, (size_t)in->tri_count * 9 * sizeof(float));
    for (size_t i = 0; i < 3 * (size_t)in->tri_count; i++)
        index[i] = (unsigned)i;

    rtcSetGeometryIntersectFilterFunction(geom, record_and_reject);
    rtcSetGeometryOccludedFilterFunction(geom, record_and_reject);
    rtcCommitGeometry(geom);
    rtcAttachGeometry(scene, geom);
    rtcReleaseGeometry(geom);
    rtcCommitScene(scene);
    return scene;
}

/* ------------------------------------------------------------------------ */
/* main                                                                       */
/* ------------------------------------------------------------------------ */

static int cmp_double(const void *a, const void *b)
{
    double x = *(const double *)a, y = *(const double *)b;
    return (x > y) - (x < y);
}

static void usage(void)
{
    fputs("usage: trace FILE [--threads N (2)] [--repeat R (3)]\n"
          "             [--mode all|occluded8|occluded1|intersect1 (all)]\n"
          "             [--robust]             set RTC_SCENE_FLAG_ROBUST (default: no flags)\n"
          "             [--quality medium|high] the BVH's build quality (medium)\n"
          "             [--expect CROSSINGS]   exit 3 if any pass finds another count\n",
          stderr);
    exit(1);
}

static long parse_long(const char *s, const char *opt, long min)
{
    char *end;
    errno = 0;
    long v = strtol(s, &end, 10);
    if (errno != 0 || *end != '\0' || v < min)
        die("bad value for %s: %s", opt, s);
    return v;
}

int main(int argc, char **argv)
{
    const char *path = NULL;
    int threads = 2, repeat = 3;
    int run_mode[MODE_COUNT] = { 1, 1, 1 };
    long long expect = -1;
    int robust = 0, high = 0;

    for (int i = 1; i < argc; i++) {
        const char *a = argv[i];
        if (strcmp(a, "--threads") == 0 && i + 1 < argc) {
            threads = (int)parse_long(argv[++i], a, 1);
            if (threads > 1024)
                die("--threads too large");
        } else if (strcmp(a, "--repeat") == 0 && i + 1 < argc) {
            repeat = (int)parse_long(argv[++i], a, 1);
            if (repeat > 1000)
                die("--repeat too large");
        } else if (strcmp(a, "--robust") == 0) {
            robust = 1;
        } else if (strcmp(a, "--quality") == 0 && i + 1 < argc) {
            const char *q = argv[++i];
            if (strcmp(q, "high") == 0)
                high = 1;
            else if (strcmp(q, "medium") != 0)
                die("unknown quality: %s", q);
        } else if (strcmp(a, "--expect") == 0 && i + 1 < argc) {
            expect = parse_long(argv[++i], a, 0);
        } else if (strcmp(a, "--mode") == 0 && i + 1 < argc) {
            const char *m = argv[++i];
            int all = strcmp(m, "all") == 0, found = all;
            for (int k = 0; k < MODE_COUNT; k++) {
                run_mode[k] = all || strcmp(m, mode_names[k]) == 0;
                found |= run_mode[k];
            }
            if (!found)
                die("unknown mode: %s", m);
        } else if (a[0] == '-' || path != NULL) {
            usage();
        } else {
            path = a;
        }
    }
    if (path == NULL)
        usage();

    Input in;
    load_input(path, &in);

    /* The device's own worker threads (used by the BVH build) are limited to
     * the same thread count as the tracing. */
    char config[64];
    snprintf(config, sizeof config, "threads=%d", threads);
    RTCDevice device = rtcNewDevice(config);
    if (device == NULL)
        die("rtcNewDevice failed (error %d)", (int)rtcGetDeviceError(NULL));
    rtcSetDeviceErrorFunction(device, on_embree_error, NULL);
    if (!rtcGetDeviceProperty(device, RTC_DEVICE_PROPERTY_FILTER_FUNCTION_SUPPORTED))
        die("this Embree build has no filter function support: all-hits is impossible");

    static const char *const tasking_names[] = { "internal", "TBB", "PPL", "unknown" };
    ssize_t tasking = rtcGetDeviceProperty(device, RTC_DEVICE_PROPERTY_TASKING_SYSTEM);
    fprintf(stderr,
            "trace: embree %s, native ray4/8/16 %d/%d/%d, tasking %s, backface culling %d, "
            "scene flags %s, build quality %s, device config \"%s\"\n",
            RTC_VERSION_STRING,
            (int)rtcGetDeviceProperty(device, RTC_DEVICE_PROPERTY_NATIVE_RAY4_SUPPORTED),
            (int)rtcGetDeviceProperty(device, RTC_DEVICE_PROPERTY_NATIVE_RAY8_SUPPORTED),
            (int)rtcGetDeviceProperty(device, RTC_DEVICE_PROPERTY_NATIVE_RAY16_SUPPORTED),
            tasking_names[tasking >= 0 && tasking <= 2 ? tasking : 3],
            (int)rtcGetDeviceProperty(device, RTC_DEVICE_PROPERTY_BACKFACE_CULLING_ENABLED),
            robust ? "ROBUST" : "NONE", high ? "HIGH" : "MEDIUM", config);

    double t0 = now_seconds();
    RTCScene scene = build_scene(device, &in, robust, high);
    double build_seconds = now_seconds() - t0;
    if (atomic_load(&embree_failed))
        die("scene build failed");

    ThreadState **ts = xrealloc(NULL, (size_t)threads * sizeof *ts);
    for (int i = 0; i < threads; i++) {
        /* Separate cache-line-aligned blocks: no false sharing of counters. */
        size_t bytes = (sizeof(ThreadState) + 63) / 64 * 64;
        ts[i] = aligned_alloc(64, bytes);
        if (ts[i] == NULL)
            die("out of memory");
        memset(ts[i], 0, bytes);
    }

    double *secs = xrealloc(NULL, (size_t)repeat * sizeof(double));
    int have_reference = 0, expect_failed = 0;
    uint64_t ref_crossings = 0, ref_fingerprint = 0;

    for (int m = 0; m < MODE_COUNT; m++) {
        if (!run_mode[m])
            continue;
        PassResult first = { 0 };
        for (int rep = 0; rep < repeat; rep++) {
            PassResult r = run_pass(scene, &in, (Mode)m, threads, ts);
            if (atomic_load(&embree_failed))
                die("tracing failed");
            secs[rep] = r.seconds;
            if (rep == 0)
                first = r;
            if (!have_reference) {
                have_reference = 1;
                ref_crossings = r.crossings;
                ref_fingerprint = r.fingerprint;
            } else if (r.crossings != ref_crossings || r.fingerprint != ref_fingerprint) {
                fprintf(stderr,
                        "trace: WARNING: %s pass %d found %llu crossings (fingerprint %016llx), "
                        "first pass found %llu (%016llx)\n",
                        mode_names[m], rep + 1, (unsigned long long)r.crossings,
                        (unsigned long long)r.fingerprint, (unsigned long long)ref_crossings,
                        (unsigned long long)ref_fingerprint);
            }
            if (expect >= 0 && r.crossings != (uint64_t)expect)
                expect_failed = 1;
        }
        qsort(secs, (size_t)repeat, sizeof(double), cmp_double);
        double median = repeat % 2 ? secs[repeat / 2]
                                   : 0.5 * (secs[repeat / 2 - 1] + secs[repeat / 2]);

        if (first.duplicates != 0 || first.out_of_range != 0)
            fprintf(stderr, "trace: %s: %llu duplicate and %llu out-of-range hits dropped\n",
                    mode_names[m], (unsigned long long)first.duplicates,
                    (unsigned long long)first.out_of_range);

        printf("{\"mode\":\"%s\",\"threads\":%d,\"triangles\":%u,\"lines\":%zu,"
               "\"crossings\":%llu,\"seconds\":%.6f,\"best_seconds\":%.6f,"
               "\"build_seconds\":%.6f,\"mcps\":%.3f,\"repeat\":%d,\"robust\":%s,"
               "\"duplicates\":%llu,\"filter_calls\":%llu,\"filter_lanes\":%llu,"
               "\"fingerprint\":\"%016llx\",\"hist\":[",
               mode_names[m], threads, in.tri_count, in.line_count,
               (unsigned long long)first.crossings, median, secs[0], build_seconds,
               (double)first.crossings / median / 1e6, repeat, robust ? "true" : "false",
               (unsigned long long)first.duplicates, (unsigned long long)first.filter_calls,
               (unsigned long long)first.filter_lanes, (unsigned long long)first.fingerprint);
        for (int k = 0; k < HIST_BINS; k++)
            printf("%s%llu", k ? "," : "", (unsigned long long)first.hist[k]);
        printf("]}\n");
        fflush(stdout);
        if (first.lines != in.line_count)
            die("internal error: traced %llu of %zu lines", (unsigned long long)first.lines,
                in.line_count);
    }

    if (expect_failed)
        fprintf(stderr, "trace: FAILED: expected %lld crossings\n", expect);

    rtcReleaseScene(scene);
    rtcReleaseDevice(device);
    for (int i = 0; i < threads; i++) {
        for (int k = 0; k < PACKET; k++)
            free(ts[i]->slot[k].hits);
        free(ts[i]->counts);
        free(ts[i]->out);
        free(ts[i]);
    }
    free(ts);
    free(secs);
    free(in.tris);
    free(in.bundles);
    free(in.origins);
    return expect_failed ? 3 : 0;
}
