/*
 * C/C++ host test of libharmonizer, built against the committed header with
 * gcc (C99) and g++ (C++17), against the shared and the static library, with
 * AddressSanitizer and UndefinedBehaviorSanitizer (see Makefile).
 *
 * Covers: version; a full sequence (color, depth, motion, coverage); in place;
 * RGBA with a 16-byte pixel stride where only RGB is color; NaN/Inf input;
 * zero size; NULL pointers; wrong struct_size; resize in the middle of a
 * sequence (implicit reset); cancel at the start, middle and end (state
 * unchanged); two sessions on two threads; frames too large for memory
 * (refused, state unchanged); frame numbers that would wrap; tile settings
 * refused at commit and bad models refused by hz_device_new; normals
 * validated and their NaN/Inf warned; hz_frame and hz_report of an older
 * header's size; albedo and denoise_normal validated; insert_id (the size
 * before it, validated, alone making the mask); a noisy frame with
 * its albedo denoised by Open Image Denoise (the real library: the pyoidn
 * wheel in the repository's .venv or HARMONIZER_OIDN_LIB; missing, the
 * test fails) and the report's denoise fields; hz_run_sequence over an EXR
 * sequence on disk, a chunk with its pre-roll (issue 22; the sequence is
 * HZ_TEST_SEQUENCE, which the Makefile writes with `harmonize synth`), its
 * frame callback, and its refusals.
 */
#include "harmonizer.h"

#include <math.h>
#include <stddef.h>
#include <pthread.h>
#include <stdio.h>
#include <stdlib.h>
#include <string.h>
#include <unistd.h>

static int checks = 0;
static int failures = 0;

#define CHECK(cond, ...)                                                                  \
    do {                                                                                  \
        checks++;                                                                         \
        if (!(cond)) {                                                                    \
            failures++;                                                                   \
            fprintf(stderr, "FAIL %s:%d: %s: ", __FILE__, __LINE__, #cond);               \
            fprintf(stderr, __VA_ARGS__);                                                 \
            fprintf(stderr, " [last error: %s]\n", hz_last_error_message());              \
        }                                                                                 \
    } while (0)

#define CHECK_OK(call) CHECK((call) == HZ_OK, "%s", #call)

/* ---- synthetic frames: a texture moving 1 px right per frame, with a hole ---- */

typedef struct frame_data {
    size_t w, h;
    float *rgba;     /* RGBA, premultiplied, alpha = coverage */
    float *depth;    /* planar depth */
    float *motion;   /* current -> previous, x right, y down */
    float *coverage; /* 1 = data, 0 = hole */
} frame_data;

static float *alloc_floats(size_t n) {
    float *p = (float *)calloc(n, sizeof(float));
    if (!p) {
        fprintf(stderr, "out of memory\n");
        exit(2);
    }
    return p;
}

static float texture(double x, double y) {
    return (float)(0.5 + 0.25 * sin(x * 0.37) * cos(y * 0.23) + 0.2 * (((int)floor(x / 6.0) + (int)floor(y / 6.0)) & 1));
}

static frame_data make_frame(size_t w, size_t h, int t) {
    frame_data f;
    size_t x, y;
    f.w = w;
    f.h = h;
    f.rgba = alloc_floats(w * h * 4);
    f.depth = alloc_floats(w * h);
    f.motion = alloc_floats(w * h * 2);
    f.coverage = alloc_floats(w * h);
    for (y = 0; y < h; y++) {
        for (x = 0; x < w; x++) {
            size_t i = y * w + x;
            int hole = x >= w / 3 && x < w / 3 + w / 6 && y >= h / 3 && y < h / 3 + h / 6;
            float c = hole ? 0.0f : 1.0f;
            float flicker = 1.0f + 0.08f * (float)((t * 37) % 5) / 5.0f;
            double sx = (double)x - t; /* the texture moves right by one pixel per frame */
            f.rgba[i * 4 + 0] = c * flicker * texture(sx, (double)y);
            f.rgba[i * 4 + 1] = c * flicker * texture(sx + 11.0, (double)y + 3.0);
            f.rgba[i * 4 + 2] = c * flicker * 0.5f;
            f.rgba[i * 4 + 3] = c;
            f.coverage[i] = c;
            f.depth[i] = 5.0f;
            f.motion[i * 2 + 0] = -1.0f; /* the surface was one pixel to the left */
            f.motion[i * 2 + 1] = 0.0f;
        }
    }
    return f;
}

static void free_frame(frame_data *f) {
    free(f->rgba);
    free(f->depth);
    free(f->motion);
    free(f->coverage);
}

static hz_image image(float *data, size_t w, size_t h, uint32_t channels, size_t pixel_stride) {
    hz_image img;
    memset(&img, 0, sizeof img);
    img.struct_size = sizeof(hz_image);
    img.format = HZ_FORMAT_F32;
    img.channels = channels;
    img.width = w;
    img.height = h;
    img.pixel_stride = pixel_stride;
    img.data = data;
    return img;
}

/* Images of one frame; the hz_frame points into it. */
typedef struct frame_desc {
    hz_image color, depth, motion, coverage;
    hz_frame frame;
} frame_desc;

static void describe(frame_desc *d, frame_data *f, int index, int with_aovs) {
    d->color = image(f->rgba, f->w, f->h, 4, 0);
    d->depth = image(f->depth, f->w, f->h, 1, 0);
    d->motion = image(f->motion, f->w, f->h, 2, 0);
    d->coverage = image(f->coverage, f->w, f->h, 1, 0);
    memset(&d->frame, 0, sizeof d->frame);
    d->frame.struct_size = sizeof(hz_frame);
    d->frame.color = &d->color;
    if (with_aovs) {
        d->frame.depth = &d->depth;
        d->frame.motion = &d->motion;
        d->frame.coverage = &d->coverage;
    }
    d->frame.frame_index = index;
    d->frame.flags = HZ_FRAME_HAS_INDEX;
    d->frame.motion_vector_scale[0] = 1.0f;
    d->frame.motion_vector_scale[1] = 1.0f;
}

static hz_session *new_session(hz_device *device, const char *backend) {
    hz_session *s = NULL;
    CHECK_OK(hz_session_new(device, &s));
    CHECK_OK(hz_session_set_string(s, "backend", backend));
    CHECK_OK(hz_session_commit(s));
    return s;
}

static int same_bits(const float *a, const float *b, size_t n) {
    return memcmp(a, b, n * sizeof(float)) == 0;
}

static hz_report report_of(hz_session *s) {
    hz_report r;
    memset(&r, 0, sizeof r);
    r.struct_size = sizeof r;
    CHECK_OK(hz_session_get_report(s, &r));
    return r;
}

/* ---- tests ---- */

static void test_version(void) {
    CHECK(strcmp(hz_version(), HZ_VERSION_STRING) == 0, "library %s, header %s", hz_version(), HZ_VERSION_STRING);
    CHECK_OK(hz_check_version(HZ_VERSION_MAJOR, HZ_VERSION_MINOR));
    CHECK(hz_check_version(HZ_VERSION_MAJOR + 1, 0) == HZ_ERROR_NOT_SUPPORTED, "another major is refused");
    CHECK(strstr(hz_last_error_message(), "major") != NULL, "message names the major version");
    {
        hz_device *d = (hz_device *)&checks; /* must be overwritten with NULL */
        CHECK(hz_device_new(HZ_VERSION_MAJOR + 1, NULL, &d) == HZ_ERROR_NOT_SUPPORTED, "device of another major");
        CHECK(d == NULL, "failed create sets NULL");
        CHECK(strncmp(hz_last_error_message(), "hz_device_new:", 14) == 0, "message names the function");
    }
    CHECK(strcmp(hz_status_name(HZ_ERROR_CANCELLED), "HZ_ERROR_CANCELLED") == 0, "status name");
}

/* A session left at its defaults runs the embedded network when ONNX Runtime is
   found (HARMONIZER_ORT_LIB, ORT_DYLIB_PATH or the project's .venv; the test
   scripts set the first), else the classical backend (auto's fallback), saying
   why in the first frame's report. With HARMONIZER_ORT_LIB set, it must be the
   network. */
static void test_default_backend(hz_device *device) {
    size_t w = 64, h = 48, i, first_warnings = 0;
    int t, must_be_neural = getenv("HARMONIZER_ORT_LIB") != NULL, neural;
    hz_session *s = NULL;
    float *out = alloc_floats(w * h * 4);
    char name[64];
    size_t len = 0;
    CHECK_OK(hz_session_new(device, &s));
    for (t = 0; t < 3; t++) {
        frame_data f = make_frame(w, h, t);
        frame_desc d;
        hz_image o = image(out, w, h, 4, 0);
        int finite = 1;
        describe(&d, &f, t, 1);
        CHECK_OK(hz_session_process(s, &d.frame, &o));
        for (i = 0; i < w * h * 4; i++) finite &= isfinite(out[i]) && out[i] >= 0.0f;
        CHECK(finite, "default backend, frame %d output finite and non-negative", t);
        i = (h / 3 + h / 12) * w + (w / 3 + w / 12);
        CHECK(f.coverage[i] == 0.0f && out[i * 4 + 3] > 0.99f, "default backend, frame %d hole alpha %f", t,
              out[i * 4 + 3]);
        if (t == 0) first_warnings = report_of(s).warning_count;
        free_frame(&f);
    }
    CHECK_OK(hz_session_get_backend_name(s, name, sizeof name, &len));
    neural = strcmp(name, "neural") == 0;
    CHECK(neural || (!must_be_neural && strcmp(name, "classical") == 0 && first_warnings > 0),
          "default backend %s (HARMONIZER_ORT_LIB %s, %zu warnings)", name, must_be_neural ? "set" : "not set",
          first_warnings);
    CHECK_OK(hz_session_get_model_name(s, name, sizeof name, &len));
    CHECK(neural ? strcmp(name, "harmonizer-small") == 0 : len == 0, "default model '%s'", name);
    free(out);
    CHECK_OK(hz_session_free(s));
}

static void test_sequence(hz_device *device) {
    size_t w = 64, h = 48, i;
    int t;
    hz_session *s = new_session(device, "classical");
    float *out = alloc_floats(w * h * 4);
    for (t = 0; t < 8; t++) {
        frame_data f = make_frame(w, h, t);
        frame_desc d;
        hz_image o = image(out, w, h, 4, 0);
        hz_report r;
        size_t history = 0, bytes = 0;
        int finite = 1;
        describe(&d, &f, 100 + t, 1);
        CHECK_OK(hz_session_process(s, &d.frame, &o));
        for (i = 0; i < w * h * 4; i++) finite &= isfinite(out[i]) && out[i] >= 0.0f;
        CHECK(finite, "frame %d output finite and non-negative", t);
        /* The hole's centre is filled: alpha (coverage after filling) is 1. */
        i = (h / 3 + h / 12) * w + (w / 3 + w / 12);
        CHECK(f.coverage[i] == 0.0f && out[i * 4 + 3] > 0.99f, "frame %d hole alpha %f", t, out[i * 4 + 3]);
        r = report_of(s);
        CHECK(r.has_frame_index && r.frame_index == 100 + t, "report index %lld", (long long)r.frame_index);
        CHECK(r.reset_reason == (t == 0 ? HZ_RESET_FIRST_FRAME : HZ_RESET_NONE), "frame %d reset %u", t,
              (unsigned)r.reset_reason);
        CHECK(r.history_used == (size_t)(t < 4 ? t : 4), "frame %d history used %zu", t, r.history_used);
        CHECK_OK(hz_session_get_history_length(s, &history));
        CHECK(history == (size_t)(t + 1 < 4 ? t + 1 : 4), "history %zu", history);
        CHECK_OK(hz_session_get_memory_bytes(s, &bytes));
        CHECK(bytes >= history * w * h * 4 * sizeof(float), "memory %zu", bytes);
        free_frame(&f);
    }
    {
        char name[32];
        size_t len = 0;
        CHECK_OK(hz_session_get_backend_name(s, name, sizeof name, &len));
        CHECK(strcmp(name, "classical") == 0 && len == 9, "backend %s", name);
        CHECK_OK(hz_session_get_model_name(s, NULL, 0, &len));
        CHECK(len == 0, "no model name for the classical backend");
    }
    CHECK_OK(hz_session_reset(s));
    {
        size_t history = 7;
        CHECK_OK(hz_session_get_history_length(s, &history));
        CHECK(history == 0, "history after reset %zu", history);
    }
    free(out);
    CHECK_OK(hz_session_free(s));
}

/* In place on an RGBA buffer where only RGB is color (16-byte stride),
 * compared with a separate output. */
static void test_in_place_strided(hz_device *device) {
    size_t w = 40, h = 30, i;
    int t;
    hz_session *a = new_session(device, "classical");
    hz_session *b = new_session(device, "classical");
    float *out = alloc_floats(w * h * 3);
    for (t = 0; t < 4; t++) {
        frame_data f = make_frame(w, h, t);
        frame_desc d;
        hz_image o = image(out, w, h, 3, 0);
        hz_image rgb_in_rgba = image(f.rgba, w, h, 3, 16);
        float *alpha_before = alloc_floats(w * h);
        int same = 1, alpha_kept = 1;
        describe(&d, &f, t, 1);
        d.color = rgb_in_rgba;
        for (i = 0; i < w * h; i++) alpha_before[i] = f.rgba[i * 4 + 3];
        CHECK_OK(hz_session_process(a, &d.frame, &o));
        CHECK_OK(hz_session_process(b, &d.frame, &rgb_in_rgba)); /* output aliases the color input */
        for (i = 0; i < w * h; i++) {
            same &= memcmp(&out[i * 3], &f.rgba[i * 4], 3 * sizeof(float)) == 0;
            alpha_kept &= f.rgba[i * 4 + 3] == alpha_before[i];
        }
        CHECK(same, "frame %d: in place equals a separate output", t);
        CHECK(alpha_kept, "frame %d: the 4th channel is left alone", t);
        free(alpha_before);
        free_frame(&f);
    }
    free(out);
    CHECK_OK(hz_session_free(a));
    CHECK_OK(hz_session_free(b));
}

typedef struct messages {
    int warnings;
    char last[512];
} messages;

static void on_message(void *user, uint32_t level, const char *text) {
    messages *m = (messages *)user;
    if (level == HZ_MESSAGE_WARNING) m->warnings++;
    strncpy(m->last, text, sizeof m->last - 1);
    m->last[sizeof m->last - 1] = 0;
}

static void test_nan_inf(hz_device *device) {
    size_t w = 16, h = 8, i;
    hz_session *s = new_session(device, "bypass");
    frame_data f = make_frame(w, h, 0);
    frame_desc d;
    float *out = alloc_floats(w * h * 4);
    hz_image o = image(out, w, h, 4, 0);
    messages m;
    int finite = 1;
    memset(&m, 0, sizeof m);
    f.rgba[0] = NAN;
    f.rgba[5] = INFINITY;
    f.rgba[10] = -INFINITY;
    f.rgba[17] = -1.0f; /* finite and negative: a color outside Rec.709 */
    f.depth[3] = NAN;
    f.motion[6] = 1e6f; /* far longer than the image */
    describe(&d, &f, 0, 1);
    CHECK_OK(hz_session_set_message_callback(s, on_message, &m));
    CHECK_OK(hz_session_process(s, &d.frame, &o));
    for (i = 0; i < w * h * 4; i++) finite &= isfinite(out[i]);
    CHECK(finite, "NaN/Inf never reach the output");
    CHECK(out[0] == 0.0f && out[5] == 0.0f && out[10] == 0.0f, "NaN and infinite samples become 0");
    CHECK(out[17] == -1.0f, "a negative (out-of-gamut) component passes through unclipped: %g", out[17]);
    CHECK(out[4] == f.rgba[4], "good samples pass through the bypass backend unchanged");
    {
        hz_report r = report_of(s);
        char text[512];
        char json[4096];
        CHECK(r.sanitized == 3, "sanitized %zu", r.sanitized);
        CHECK_OK(hz_session_get_report_json(s, json, sizeof json, NULL));
        CHECK(strstr(json, "\"out_of_gamut\":1") != NULL, "report counts the out-of-gamut pixel: %s", json);
        CHECK(r.warning_count >= 1, "warnings %zu", r.warning_count);
        CHECK_OK(hz_session_get_report_warning(s, 0, text, sizeof text, NULL));
        CHECK(strstr(text, "NaN") != NULL, "warning text: %s", text);
        CHECK(hz_session_get_report_warning(s, 99, text, sizeof text, NULL) == HZ_ERROR_INVALID_ARGUMENT,
              "warning index out of range");
    }
    CHECK(m.warnings >= 3, "message callback: %d warnings (color NaN, AOV NaN, motion), last: %s", m.warnings, m.last);
    CHECK(strstr(m.last, "longer than the image") != NULL, "motion warning: %s", m.last);
    free(out);
    free_frame(&f);
    CHECK_OK(hz_session_free(s));
}

static void test_bad_arguments(hz_device *device) {
    size_t w = 8, h = 4;
    hz_session *s = new_session(device, "bypass");
    frame_data f = make_frame(w, h, 0);
    frame_desc d;
    float *out = alloc_floats(w * h * 4);
    hz_image o = image(out, w, h, 4, 0);
    hz_image bad;
    hz_frame fr;
    describe(&d, &f, 0, 1);

    /* NULL pointers */
    CHECK(hz_session_process(NULL, &d.frame, &o) == HZ_ERROR_INVALID_ARGUMENT, "NULL session");
    CHECK(strstr(hz_last_error_message(), "session is NULL") != NULL, "message");
    CHECK(hz_session_process(s, NULL, &o) == HZ_ERROR_INVALID_ARGUMENT, "NULL frame");
    CHECK(hz_session_process(s, &d.frame, NULL) == HZ_ERROR_INVALID_ARGUMENT, "NULL output");
    fr = d.frame;
    fr.color = NULL;
    CHECK(hz_session_process(s, &fr, &o) == HZ_ERROR_INVALID_ARGUMENT, "NULL color");
    bad = d.color;
    bad.data = NULL;
    fr.color = &bad;
    CHECK(hz_session_process(s, &fr, &o) == HZ_ERROR_INVALID_ARGUMENT, "NULL data");
    CHECK(strstr(hz_last_error_message(), "color: data is NULL") != NULL, "%s", hz_last_error_message());
    CHECK(hz_session_new(device, NULL) == HZ_ERROR_INVALID_ARGUMENT, "NULL out_session");
    {
        hz_session *none = (hz_session *)&checks;
        CHECK(hz_session_new(NULL, &none) == HZ_ERROR_INVALID_ARGUMENT && none == NULL, "NULL device");
    }
    CHECK(hz_session_set_int(s, NULL, 1) == HZ_ERROR_INVALID_ARGUMENT, "NULL name");
    CHECK(hz_session_set_string(s, "backend", NULL) == HZ_ERROR_INVALID_ARGUMENT, "NULL value");
    CHECK_OK(hz_session_free(NULL));
    CHECK_OK(hz_device_free(NULL));

    /* zero size */
    bad = d.color;
    bad.width = 0;
    fr = d.frame;
    fr.color = &bad;
    CHECK(hz_session_process(s, &fr, &o) == HZ_ERROR_INVALID_ARGUMENT, "zero width");
    CHECK(strstr(hz_last_error_message(), "0x4 is empty") != NULL, "%s", hz_last_error_message());
    bad.width = w;
    bad.height = 0;
    CHECK(hz_session_process(s, &fr, &o) == HZ_ERROR_INVALID_ARGUMENT, "zero height");

    /* sizes that overflow or exceed what the strides allow */
    bad = d.color;
    bad.width = (size_t)-1 / 8;
    bad.height = 16;
    CHECK(hz_session_process(s, &fr, &o) == HZ_ERROR_INVALID_ARGUMENT, "overflowing size");
    CHECK(strstr(hz_last_error_message(), "overflows") != NULL, "%s", hz_last_error_message());
    bad = d.color;
    bad.pixel_stride = 8; /* smaller than 4 channels of 4 bytes */
    CHECK(hz_session_process(s, &fr, &o) == HZ_ERROR_INVALID_ARGUMENT, "stride too small");
    bad = d.color;
    bad.offset = 2;
    CHECK(hz_session_process(s, &fr, &o) == HZ_ERROR_INVALID_ARGUMENT, "misaligned offset");
    bad = d.color;
    bad.format = 0;
    CHECK(hz_session_process(s, &fr, &o) == HZ_ERROR_INVALID_ARGUMENT, "format 0");

    /* wrong struct_size */
    fr = d.frame;
    fr.struct_size = sizeof(hz_frame) - 4;
    CHECK(hz_session_process(s, &fr, &o) == HZ_ERROR_INVALID_ARGUMENT, "hz_frame.struct_size");
    CHECK(strstr(hz_last_error_message(), "hz_frame.struct_size") != NULL, "%s", hz_last_error_message());
    bad = d.color;
    bad.struct_size = 0;
    fr = d.frame;
    fr.color = &bad;
    CHECK(hz_session_process(s, &fr, &o) == HZ_ERROR_INVALID_ARGUMENT, "hz_image.struct_size");
    {
        hz_device_options opts;
        hz_device *dev = NULL;
        hz_report r;
        memset(&opts, 0, sizeof opts);
        opts.struct_size = 1;
        CHECK(hz_device_new(HZ_VERSION_MAJOR, &opts, &dev) == HZ_ERROR_INVALID_ARGUMENT && dev == NULL,
              "hz_device_options.struct_size");
        memset(&r, 0, sizeof r);
        r.struct_size = sizeof r + 8;
        CHECK(hz_session_get_report(s, &r) == HZ_ERROR_INVALID_ARGUMENT, "hz_report.struct_size");
    }

    /* parameters */
    CHECK(hz_session_set_int(s, "context_frames", 9) == HZ_ERROR_INVALID_ARGUMENT, "out of range");
    CHECK(strstr(hz_last_error_message(), "context_frames") != NULL, "%s", hz_last_error_message());
    CHECK(hz_session_set_float(s, "no_such_parameter", 1.0) == HZ_ERROR_INVALID_ARGUMENT, "unknown");
    CHECK(hz_session_set_string(s, "backend", "gpu") == HZ_ERROR_INVALID_ARGUMENT, "bad backend");
    {
        int64_t k = 0;
        double strength = 0.0;
        bool fill = false;
        hz_param_type type = HZ_PARAM_STRING;
        CHECK_OK(hz_session_set_int(s, "context_frames", 2));
        CHECK_OK(hz_session_get_int(s, "context_frames", &k));
        CHECK(k == 2, "staged value %lld", (long long)k);
        CHECK(hz_session_process(s, &d.frame, &o) == HZ_ERROR_INVALID_OPERATION, "uncommitted parameters");
        CHECK_OK(hz_session_commit(s));
        CHECK_OK(hz_session_process(s, &d.frame, &o));
        CHECK_OK(hz_session_get_float(s, "strength", &strength));
        CHECK(strength == 1.0, "strength %f", strength);
        CHECK_OK(hz_session_get_bool(s, "fill_holes", &fill));
        CHECK(fill, "fill_holes");
        CHECK_OK(hz_session_get_type(s, "strength", &type));
        CHECK(type == HZ_PARAM_FLOAT, "type %u", (unsigned)type);
        CHECK(hz_session_get_int(s, "backend", &k) == HZ_ERROR_INVALID_ARGUMENT, "wrong type");
    }
    /* output of another size is refused and untouched */
    {
        hz_image small = image(out, w - 1, h, 4, 0);
        CHECK(hz_session_process(s, &d.frame, &small) == HZ_ERROR_INVALID_ARGUMENT, "output size");
    }
    free(out);
    free_frame(&f);
    CHECK_OK(hz_session_free(s));
}

static void test_resize(hz_device *device) {
    hz_session *s = new_session(device, "classical");
    int t;
    for (t = 0; t < 5; t++) {
        size_t w = t < 3 ? 48 : 24, h = t < 3 ? 32 : 16;
        frame_data f = make_frame(w, h, t);
        frame_desc d;
        float *out = alloc_floats(w * h * 4);
        hz_image o = image(out, w, h, 4, 0);
        hz_report r;
        describe(&d, &f, t, 1);
        CHECK_OK(hz_session_process(s, &d.frame, &o));
        r = report_of(s);
        if (t == 3) CHECK(r.reset_reason == HZ_RESET_SIZE_CHANGED, "reset %u", (unsigned)r.reset_reason);
        if (t == 4) CHECK(r.reset_reason == HZ_RESET_NONE && r.history_used == 1, "after resize");
        free(out);
        free_frame(&f);
    }
    CHECK_OK(hz_session_free(s));
}

typedef struct cancel_state {
    int calls;
    int cancel_at; /* return false on this call (1-based); 0 = never */
} cancel_state;

static bool on_progress(void *user, double p) {
    cancel_state *c = (cancel_state *)user;
    c->calls++;
    if (p < 0.0 || p > 1.0) return false;
    return c->cancel_at == 0 || c->calls < c->cancel_at;
}

static void test_cancel(hz_device *device) {
    size_t w = 40, h = 24, n = w * h * 4;
    int total, which, t;
    cancel_state probe = {0, 0};
    {
        hz_session *s = new_session(device, "classical");
        frame_data f = make_frame(w, h, 0);
        frame_desc d;
        float *out = alloc_floats(n);
        hz_image o = image(out, w, h, 4, 0);
        describe(&d, &f, 0, 1);
        CHECK_OK(hz_session_set_progress_callback(s, on_progress, &probe));
        CHECK_OK(hz_session_process(s, &d.frame, &o));
        free(out);
        free_frame(&f);
        CHECK_OK(hz_session_free(s));
    }
    total = probe.calls;
    CHECK(total >= 2, "progress calls per frame: %d", total);
    for (which = 0; which < 3; which++) {
        int cancel_at = which == 0 ? 1 : which == 1 ? (total + 1) / 2 : total;
        hz_session *ref = new_session(device, "classical");
        hz_session *s = new_session(device, "classical");
        float *out_ref = alloc_floats(n), *out = alloc_floats(n);
        for (t = 0; t < 5; t++) {
            frame_data f = make_frame(w, h, t);
            frame_desc d;
            hz_image o_ref = image(out_ref, w, h, 4, 0), o = image(out, w, h, 4, 0);
            describe(&d, &f, t, 1);
            if (t == 2) {
                cancel_state c = {0, cancel_at};
                float *sentinel = alloc_floats(n);
                hz_image os = image(sentinel, w, h, 4, 0);
                size_t i, history_before = 0, history_after = 1;
                int untouched = 1;
                for (i = 0; i < n; i++) sentinel[i] = 7.0f;
                CHECK_OK(hz_session_get_history_length(s, &history_before));
                CHECK_OK(hz_session_set_progress_callback(s, on_progress, &c));
                CHECK(hz_session_process(s, &d.frame, &os) == HZ_ERROR_CANCELLED, "cancel at %d of %d", cancel_at,
                      total);
                CHECK(strstr(hz_last_error_message(), "cancelled") != NULL, "%s", hz_last_error_message());
                CHECK_OK(hz_session_set_progress_callback(s, NULL, NULL));
                for (i = 0; i < n; i++) untouched &= sentinel[i] == 7.0f;
                CHECK(untouched, "a cancelled call leaves the output untouched");
                CHECK_OK(hz_session_get_history_length(s, &history_after));
                CHECK(history_before == history_after, "history %zu -> %zu", history_before, history_after);
                free(sentinel);
            }
            CHECK_OK(hz_session_process(ref, &d.frame, &o_ref));
            CHECK_OK(hz_session_process(s, &d.frame, &o));
            CHECK(same_bits(out_ref, out, n), "cancel at %d: frame %d equals the session that never saw it",
                  cancel_at, t);
            free_frame(&f);
        }
        free(out_ref);
        free(out);
        CHECK_OK(hz_session_free(ref));
        CHECK_OK(hz_session_free(s));
    }
}

/* A callback that calls back into its own session is refused, not deadlocked. */
typedef struct reentry {
    hz_session *session;
    hz_status status;
} reentry;

static bool reenter(void *user, double p) {
    reentry *r = (reentry *)user;
    size_t n = 0;
    (void)p;
    r->status = hz_session_get_history_length(r->session, &n);
    return true;
}

static void test_reentry(hz_device *device) {
    size_t w = 8, h = 4;
    hz_session *s = new_session(device, "bypass");
    frame_data f = make_frame(w, h, 0);
    frame_desc d;
    float *out = alloc_floats(w * h * 4);
    hz_image o = image(out, w, h, 4, 0);
    reentry r = {NULL, HZ_OK};
    r.session = s;
    describe(&d, &f, 0, 0);
    CHECK_OK(hz_session_set_progress_callback(s, reenter, &r));
    CHECK_OK(hz_session_process(s, &d.frame, &o));
    CHECK(r.status == HZ_ERROR_INVALID_OPERATION, "re-entry status %u", (unsigned)r.status);
    free(out);
    free_frame(&f);
    CHECK_OK(hz_session_free(s));
}

/* ---- two sessions on two threads: same results as one after the other ---- */

typedef struct worker {
    hz_device *device;
    int seed;
    size_t w, h;
    float *out; /* last output */
    int ok;
} worker;

static void *run_worker(void *arg) {
    worker *wk = (worker *)arg;
    hz_session *s = NULL;
    int t;
    wk->ok = hz_session_new(wk->device, &s) == HZ_OK && hz_session_set_string(s, "backend", "classical") == HZ_OK &&
             hz_session_commit(s) == HZ_OK;
    for (t = 0; wk->ok && t < 6; t++) {
        frame_data f = make_frame(wk->w, wk->h, t + wk->seed);
        frame_desc d;
        hz_image o = image(wk->out, wk->w, wk->h, 4, 0);
        describe(&d, &f, t, 1);
        wk->ok = hz_session_process(s, &d.frame, &o) == HZ_OK;
        free_frame(&f);
    }
    hz_session_free(s);
    return NULL;
}

static void test_threads(hz_device *device) {
    worker seq[2], par[2];
    pthread_t th[2];
    int k;
    for (k = 0; k < 2; k++) {
        seq[k].device = par[k].device = device;
        seq[k].seed = par[k].seed = 10 * k;
        seq[k].w = par[k].w = 56 + 8 * (size_t)k;
        seq[k].h = par[k].h = 40;
        seq[k].out = alloc_floats(seq[k].w * seq[k].h * 4);
        par[k].out = alloc_floats(par[k].w * par[k].h * 4);
        run_worker(&seq[k]);
        CHECK(seq[k].ok, "sequential run %d", k);
    }
    for (k = 0; k < 2; k++) CHECK(pthread_create(&th[k], NULL, run_worker, &par[k]) == 0, "thread %d", k);
    for (k = 0; k < 2; k++) pthread_join(th[k], NULL);
    for (k = 0; k < 2; k++) {
        CHECK(par[k].ok, "threaded run %d", k);
        CHECK(same_bits(seq[k].out, par[k].out, par[k].w * par[k].h * 4), "thread %d equals the sequential run", k);
        free(seq[k].out);
        free(par[k].out);
    }
}

/* ---- regressions of issues 2, 11, 12 and 13 ---- */

/* Issue 2: a frame too large to allocate aborted the host. It is refused with
 * HZ_ERROR_OUT_OF_MEMORY naming the size and the limit, before the library
 * allocates anything or reads the (here tiny) buffer, and the session goes
 * on as if the call never happened. */
static void check_too_large(hz_session *s, size_t side, const char *limit_text) {
    float tiny[16];
    hz_image huge = image(tiny, side, side, 3, 0), huge_out = image(tiny, side, side, 4, 0);
    hz_frame fr;
    char size_text[64];
    memset(&fr, 0, sizeof fr);
    fr.struct_size = sizeof fr;
    fr.color = &huge;
    fr.frame_index = 2;
    fr.flags = HZ_FRAME_HAS_INDEX;
    sprintf(size_text, "%zux%zu", side, side);
    CHECK(hz_session_process(s, &fr, &huge_out) == HZ_ERROR_OUT_OF_MEMORY, "%s frame", size_text);
    CHECK(strstr(hz_last_error_message(), size_text) != NULL && strstr(hz_last_error_message(), limit_text) != NULL,
          "message names %s and %s: %s", size_text, limit_text, hz_last_error_message());
}

static void test_too_large(hz_device *device) {
    size_t w = 64, h = 48, n = w * h * 4;
    int pass, t;
    hz_device *limited = NULL;
    hz_device_options opts;
    memset(&opts, 0, sizeof opts);
    opts.struct_size = sizeof opts;
    opts.threads = 2;
    opts.memory_limit = 64u << 20;
    CHECK_OK(hz_device_new(HZ_VERSION_MAJOR, &opts, &limited));
    if (!limited) return;
    for (pass = 0; pass < 2; pass++) {
        hz_device *dev = pass == 0 ? device : limited;
        hz_session *ref = new_session(dev, "classical");
        hz_session *s = new_session(dev, "classical");
        float *out_ref = alloc_floats(n), *out = alloc_floats(n);
        for (t = 0; t < 4; t++) {
            frame_data f = make_frame(w, h, t);
            frame_desc d;
            hz_image o_ref = image(out_ref, w, h, 4, 0), o = image(out, w, h, 4, 0);
            describe(&d, &f, t, 1);
            if (t == 2) {
                size_t history_before = 0, history_after = 1;
                hz_report before = report_of(s), after;
                CHECK_OK(hz_session_get_history_length(s, &history_before));
                if (pass == 0) {
                    check_too_large(s, (size_t)1 << 20, "memory of this machine");
                    check_too_large(s, 60000, "memory of this machine");
                } else {
                    check_too_large(s, 20000, "device memory_limit of 67108864 bytes");
                }
                CHECK_OK(hz_session_get_history_length(s, &history_after));
                CHECK(history_before == history_after, "history %zu -> %zu", history_before, history_after);
                after = report_of(s);
                CHECK(after.frame_index == before.frame_index, "the report is the last good frame's");
            }
            CHECK_OK(hz_session_process(ref, &d.frame, &o_ref));
            CHECK_OK(hz_session_process(s, &d.frame, &o));
            CHECK(same_bits(out_ref, out, n), "pass %d: frame %d equals the session that never saw the large frame",
                  pass, t);
            free_frame(&f);
        }
        free(out_ref);
        free(out);
        CHECK_OK(hz_session_free(ref));
        CHECK_OK(hz_session_free(s));
    }
    CHECK_OK(hz_device_free(limited));
}

/* Issue 11: INT64_MAX then INT64_MIN counted as consecutive frame numbers. */
static void test_index_wrap(hz_device *device) {
    size_t w = 32, h = 24;
    hz_session *s = new_session(device, "classical");
    float *out = alloc_floats(w * h * 4);
    int t;
    for (t = 0; t < 2; t++) {
        frame_data f = make_frame(w, h, t);
        frame_desc d;
        hz_image o = image(out, w, h, 4, 0);
        hz_report r;
        describe(&d, &f, 0, 1);
        d.frame.frame_index = t == 0 ? INT64_MAX : INT64_MIN;
        CHECK_OK(hz_session_process(s, &d.frame, &o));
        r = report_of(s);
        if (t == 1) CHECK(r.reset_reason == HZ_RESET_FRAME_GAP, "INT64_MAX -> INT64_MIN: reset %u", (unsigned)r.reset_reason);
        free_frame(&f);
    }
    free(out);
    CHECK_OK(hz_session_free(s));
}

static const char *IDENTITY_MANIFEST =
    "{\"format_version\": 1, \"name\": \"identity\", \"version\": \"1.0.0\", \"context_frames\": 0,"
    " \"input\": {\"name\": \"input\", \"channels\": [\"color.r\", \"color.g\", \"color.b\"]},"
    " \"output\": {\"name\": \"output\", \"channels\": [\"color.r\", \"color.g\", \"color.b\"]},"
    " \"residual\": false, \"premultiplied\": true,"
    " \"encoding\": {\"kind\": \"log\", \"key\": 0.18, \"exposure\": \"frame\", \"log_range\": 8.0},"
    " \"tile_size\": 64, \"tile_overlap\": 8, \"spatial_multiple\": 16}";

static int write_file(const char *path, const char *text) {
    FILE *f = fopen(path, "wb");
    if (!f) return 0;
    fputs(text, f);
    return fclose(f) == 0;
}

/* Issue 12: tile settings that fail every frame are refused at commit; a
 * missing or garbage model is refused by hz_device_new, naming it. */
static void test_settings_and_models(hz_device *device) {
    hz_session *s = NULL;
    hz_status st;
    CHECK_OK(hz_session_new(device, &s));
    CHECK_OK(hz_session_set_string(s, "backend", "neural"));
    st = hz_session_commit(s);
    if (st == HZ_ERROR_RUNTIME_MISSING) {
        fprintf(stderr,
                "NOT TESTED: tile settings at commit need ONNX Runtime for the neural backend (%s); "
                "run scripts/setup-venv.sh or set HARMONIZER_ORT_LIB\n",
                hz_last_error_message());
        CHECK(getenv("HARMONIZER_ORT_LIB") == NULL, "HARMONIZER_ORT_LIB is set but the runtime is missing");
    } else {
        static const struct {
            int64_t tile, overlap;
        } bad[] = {{32, 16}, {1, 0}, {64, 64}};
        size_t i;
        int64_t v = -1;
        CHECK(st == HZ_OK, "commit backend neural: %s", hz_status_name(st));
        for (i = 0; i < sizeof bad / sizeof bad[0]; i++) {
            CHECK_OK(hz_session_set_int(s, "tile_size", bad[i].tile));
            CHECK_OK(hz_session_set_int(s, "tile_overlap", bad[i].overlap));
            CHECK(hz_session_commit(s) == HZ_ERROR_INVALID_ARGUMENT, "tile_size %lld tile_overlap %lld",
                  (long long)bad[i].tile, (long long)bad[i].overlap);
            CHECK(strstr(hz_last_error_message(), "tile_size") != NULL &&
                      strstr(hz_last_error_message(), "tile_overlap") != NULL,
                  "message names the parameters: %s", hz_last_error_message());
        }
        CHECK_OK(hz_session_set_int(s, "tile_size", 0));
        CHECK_OK(hz_session_set_int(s, "tile_overlap", 0));
        CHECK_OK(hz_session_commit(s));
        CHECK_OK(hz_session_get_int(s, "tile_size", &v));
        CHECK(v == 0, "tile_size %lld", (long long)v);
    }
    CHECK_OK(hz_session_free(s));

    {
        char garbage[256], manifest[256], missing[256];
        static const unsigned char not_onnx[] = "\x08\x07 this is not an ONNX model";
        hz_device_options opts;
        hz_device *dev = (hz_device *)&checks;
        long pid = (long)getpid();
        sprintf(garbage, "/tmp/harmonizer_c_test_%ld_garbage.onnx", pid);
        sprintf(manifest, "/tmp/harmonizer_c_test_%ld_garbage.json", pid);
        sprintf(missing, "/tmp/harmonizer_c_test_%ld_missing.onnx", pid);
        CHECK(write_file(garbage, "this is not an ONNX model") && write_file(manifest, IDENTITY_MANIFEST),
              "write %s", garbage);
        memset(&opts, 0, sizeof opts);
        opts.struct_size = sizeof opts;
        opts.model_path = missing;
        CHECK(hz_device_new(HZ_VERSION_MAJOR, &opts, &dev) == HZ_ERROR_IO && dev == NULL, "missing model file");
        if (dev) hz_device_free(dev);
        dev = NULL;
        CHECK(strstr(hz_last_error_message(), missing) != NULL, "message names the path: %s", hz_last_error_message());
        opts.model_path = garbage;
        CHECK(hz_device_new(HZ_VERSION_MAJOR, &opts, &dev) == HZ_ERROR_MODEL && dev == NULL, "garbage model file");
        if (dev) hz_device_free(dev);
        dev = NULL;
        CHECK(strstr(hz_last_error_message(), garbage) != NULL &&
                  strstr(hz_last_error_message(), "not an ONNX model") != NULL,
              "message names the path: %s", hz_last_error_message());
        opts.model_path = NULL;
        opts.model_data = not_onnx;
        opts.model_data_size = sizeof not_onnx - 1;
        opts.model_manifest = IDENTITY_MANIFEST;
        CHECK(hz_device_new(HZ_VERSION_MAJOR, &opts, &dev) == HZ_ERROR_MODEL && dev == NULL, "garbage model bytes");
        if (dev) hz_device_free(dev);
        dev = NULL;
        CHECK(strstr(hz_last_error_message(), "in-memory model") != NULL, "%s", hz_last_error_message());
        remove(garbage);
        remove(manifest);
    }
}

/* Issue 13: normals are validated like the other inputs and their NaN/Inf
 * samples warned; the classical backend gives the same output without them. */
static void test_normals(hz_device *device) {
    size_t w = 24, h = 16, i, n = w * h * 4;
    hz_session *a = new_session(device, "classical");
    hz_session *b = new_session(device, "classical");
    frame_data f = make_frame(w, h, 0);
    frame_desc d;
    float *normal = alloc_floats(w * h * 3), *out_a = alloc_floats(n), *out_b = alloc_floats(n);
    hz_image o_a = image(out_a, w, h, 4, 0), o_b = image(out_b, w, h, 4, 0);
    hz_image nrm = image(normal, w, h, 3, 0);
    messages m;
    memset(&m, 0, sizeof m);
    for (i = 0; i < w * h; i++) normal[i * 3 + 2] = -1.0f;
    normal[1] = NAN;
    normal[7] = INFINITY;
    describe(&d, &f, 0, 1);
    CHECK_OK(hz_session_process(b, &d.frame, &o_b));
    d.frame.normal = &nrm;
    CHECK_OK(hz_session_set_message_callback(a, on_message, &m));
    CHECK_OK(hz_session_process(a, &d.frame, &o_a));
    CHECK(same_bits(out_a, out_b, n), "the classical backend's output does not depend on the normals");
    CHECK(m.warnings >= 1 && strstr(m.last, "2 normal samples were NaN or infinite") != NULL, "normals warning: %s",
          m.last);
    nrm.channels = 2;
    CHECK(hz_session_process(a, &d.frame, &o_a) == HZ_ERROR_INVALID_ARGUMENT, "normals of 2 channels");
    CHECK(strstr(hz_last_error_message(), "normal") != NULL, "%s", hz_last_error_message());
    nrm.channels = 3;
    nrm.width = w / 2;
    CHECK(hz_session_process(a, &d.frame, &o_a) == HZ_ERROR_INVALID_ARGUMENT, "normals of another size");
    free(normal);
    free(out_a);
    free(out_b);
    free_frame(&f);
    CHECK_OK(hz_session_free(a));
    CHECK_OK(hz_session_free(b));
}

/* ---- issue 20: albedo and denoise_normal in hz_frame, the denoise report ---- */

/* hz_frame and hz_report as the headers before the denoise fields declared
 * them: what a host built against them passes. */
typedef struct hz_frame_0_1_0 {
    size_t struct_size;
    const hz_image *color, *depth, *motion, *normal, *coverage, *insert_mask;
    const float *world_to_camera, *world_to_ndc;
    int64_t frame_index;
    uint32_t flags;
    float motion_vector_scale[2];
} hz_frame_0_1_0;

typedef struct hz_report_0_1_0 {
    size_t struct_size;
    int64_t frame_index;
    bool has_frame_index;
    hz_reset_reason reset_reason;
    size_t history_used, sanitized, warning_count;
    double total_ms;
} hz_report_0_1_0;

static void test_older_struct_sizes(hz_device *device) {
    size_t w = 16, h = 8, i;
    hz_session *s = new_session(device, "bypass");
    frame_data f = make_frame(w, h, 0);
    frame_desc d;
    float *one = alloc_floats(w * h), *out = alloc_floats(w * h * 4);
    hz_image o = image(out, w, h, 4, 0), bad_albedo = image(one, w, h, 1, 0);
    hz_frame_0_1_0 *old = (hz_frame_0_1_0 *)malloc(sizeof *old);
    hz_report report;
    hz_report_0_1_0 old_report;
    const unsigned char *bytes = (const unsigned char *)&report;
    int untouched = 1, same = 1;
    char decision[64];
    size_t len = 99;
    CHECK(sizeof(hz_frame_0_1_0) < sizeof(hz_frame) && sizeof(hz_report_0_1_0) < sizeof(hz_report),
          "the structs grew: %zu -> %zu, %zu -> %zu", sizeof(hz_frame_0_1_0), sizeof(hz_frame),
          sizeof(hz_report_0_1_0), sizeof(hz_report));
    describe(&d, &f, 3, 1);
    /* The appended fields hold an albedo that would be refused. */
    d.frame.albedo = &bad_albedo;
    d.frame.denoise_normal = &bad_albedo;
    CHECK(hz_session_process(s, &d.frame, &o) == HZ_ERROR_INVALID_ARGUMENT, "1-channel albedo");
    CHECK(strstr(hz_last_error_message(), "albedo: needs 3 channel(s), got 1") != NULL, "%s", hz_last_error_message());
    /* With the old size they are not read. */
    d.frame.struct_size = sizeof(hz_frame_0_1_0);
    CHECK_OK(hz_session_process(s, &d.frame, &o));
    d.frame.struct_size = sizeof(hz_frame_0_1_0) + 8;
    CHECK(hz_session_process(s, &d.frame, &o) == HZ_ERROR_INVALID_ARGUMENT, "a size between the two");
    CHECK(strstr(hz_last_error_message(), "hz_frame.struct_size") != NULL, "%s", hz_last_error_message());
    /* A struct that is only as large as the old header's (on the heap). */
    if (old) {
        memset(old, 0, sizeof *old);
        old->struct_size = sizeof *old;
        old->color = &d.color;
        old->depth = &d.depth;
        old->motion = &d.motion;
        old->coverage = &d.coverage;
        old->motion_vector_scale[0] = old->motion_vector_scale[1] = 1.0f;
        old->frame_index = 4;
        old->flags = HZ_FRAME_HAS_INDEX;
        CHECK_OK(hz_session_process(s, (const hz_frame *)(const void *)old, &o));
        for (i = 0; i < w * h * 4; i++) same &= out[i] == f.rgba[i];
        CHECK(same, "bypass returns the old-size frame's color");
        free(old);
    }
    /* The old hz_report: nothing is written past it. */
    memset(&report, 0xAB, sizeof report);
    report.struct_size = sizeof(hz_report_0_1_0);
    CHECK_OK(hz_session_get_report(s, &report));
    for (i = sizeof(hz_report_0_1_0); i < sizeof(hz_report); i++) untouched &= bytes[i] == 0xAB;
    CHECK(untouched, "nothing written past the old hz_report");
    memcpy(&old_report, &report, sizeof old_report);
    CHECK(old_report.struct_size == sizeof old_report && old_report.has_frame_index && old_report.frame_index == 4 &&
              old_report.reset_reason == HZ_RESET_NONE,
          "old report: index %lld, reset %u", (long long)old_report.frame_index, (unsigned)old_report.reset_reason);
    report.struct_size = sizeof(hz_report_0_1_0) + 1;
    CHECK(hz_session_get_report(s, &report) == HZ_ERROR_INVALID_ARGUMENT, "hz_report.struct_size between the two");
    report = report_of(s);
    CHECK(!report.denoised && !report.has_noise_level && report.noise_level == 0.0f, "no denoise on bypass");
    CHECK_OK(hz_session_get_report_denoise_decision(s, decision, sizeof decision, &len));
    CHECK(len == 0 && decision[0] == 0, "no decision on the second frame: %s", decision);
    free(one);
    free(out);
    free_frame(&f);
    CHECK_OK(hz_session_free(s));
}

/* insert_id, appended to hz_frame: a host passing the size before it is
 * not read (here an id image that would be refused); it is validated like
 * the other images; alone it makes the insert mask (1 where the id is above
 * 0), so a classical session gives the same output as with that mask. */
static void test_insert_id(hz_device *device) {
    size_t w = 48, h = 32, x, y;
    size_t before_ids = offsetof(hz_frame, insert_id);
    hz_session *s = new_session(device, "classical");
    float *rgba = alloc_floats(w * h * 4), *ids = alloc_floats(w * h), *mask = alloc_floats(w * h);
    float *out = alloc_floats(w * h * 4), *with_mask = alloc_floats(w * h * 4);
    hz_image c = image(rgba, w, h, 4, 0), o = image(out, w, h, 4, 0), id_img = image(ids, w, h, 1, 0);
    hz_image m = image(mask, w, h, 1, 0), small = id_img;
    hz_frame fr;
    int darker;
    /* The box's own filter (match_tone) is what its id changes. */
    CHECK_OK(hz_session_set_bool(s, "match_tone", 1));
    CHECK_OK(hz_session_commit(s));
    for (y = 0; y < h; y++) {
        for (x = 0; x < w; x++) {
            /* A grey ground, a box 8 times too bright on it (id 3). */
            int inside = x >= 16 && x < 32 && y >= 8 && y < 24;
            float v = inside ? 4.0f : 0.5f;
            size_t i = y * w + x;
            rgba[4 * i] = rgba[4 * i + 1] = rgba[4 * i + 2] = v;
            rgba[4 * i + 3] = 1.0f;
            ids[i] = inside ? 3.0f : 0.0f;
            mask[i] = inside ? 1.0f : 0.0f;
        }
    }
    CHECK(before_ids < sizeof(hz_frame), "insert_id is appended: %zu of %zu", before_ids, sizeof(hz_frame));
    small.width = w / 2;
    memset(&fr, 0, sizeof fr);
    fr.struct_size = sizeof fr;
    fr.color = &c;
    fr.flags = HZ_FRAME_RESET;
    fr.insert_id = &small;
    CHECK(hz_session_process(s, &fr, &o) == HZ_ERROR_INVALID_ARGUMENT, "a 24x32 insert_id");
    CHECK(strstr(hz_last_error_message(), "insert_id: size 24x32 differs from color 48x32") != NULL, "%s",
          hz_last_error_message());
    fr.struct_size = before_ids;
    CHECK_OK(hz_session_process(s, &fr, &o));
    fr.struct_size = sizeof fr;
    fr.insert_id = &id_img;
    CHECK_OK(hz_session_process(s, &fr, &o));
    darker = out[4 * (16 * w + 24)] < 3.5f;
    CHECK(darker, "the box named by its id is harmonized: %f", out[4 * (16 * w + 24)]);
    fr.insert_id = NULL;
    fr.insert_mask = &m;
    o = image(with_mask, w, h, 4, 0);
    CHECK_OK(hz_session_process(s, &fr, &o));
    CHECK(same_bits(out, with_mask, w * h * 4), "ids alone give the output of the same mask");
    free(rgba);
    free(ids);
    free(mask);
    free(out);
    free(with_mask);
    CHECK_OK(hz_session_free(s));
}

/* albedo and denoise_normal are validated like the other images; the errors
 * name the field. */
static void test_albedo_validated(hz_device *device) {
    size_t w = 16, h = 8;
    int field;
    hz_session *s = new_session(device, "bypass");
    frame_data f = make_frame(w, h, 0);
    frame_desc d;
    float *aux = alloc_floats(w * h * 3), *out = alloc_floats(w * h * 4);
    hz_image o = image(out, w, h, 4, 0), good = image(aux, w, h, 3, 0), bad;
    for (field = 0; field < 2; field++) {
        const char *name = field == 0 ? "albedo" : "denoise_normal";
        char text[128];
        describe(&d, &f, 0, 1);
        if (field == 0)
            d.frame.albedo = &bad;
        else
            d.frame.denoise_normal = &bad;
        bad = good;
        bad.channels = 2;
        sprintf(text, "%s: needs 3 channel(s), got 2", name);
        CHECK(hz_session_process(s, &d.frame, &o) == HZ_ERROR_INVALID_ARGUMENT, "2-channel %s", name);
        CHECK(strstr(hz_last_error_message(), text) != NULL, "%s", hz_last_error_message());
        bad = good;
        bad.height = h / 2;
        sprintf(text, "%s: size 16x4 differs from color 16x8", name);
        CHECK(hz_session_process(s, &d.frame, &o) == HZ_ERROR_INVALID_ARGUMENT, "%s of another size", name);
        CHECK(strstr(hz_last_error_message(), text) != NULL, "%s", hz_last_error_message());
        bad = good;
        bad.struct_size = 0;
        sprintf(text, "%s: hz_image.struct_size is 0", name);
        CHECK(hz_session_process(s, &d.frame, &o) == HZ_ERROR_INVALID_ARGUMENT, "%s struct_size", name);
        CHECK(strstr(hz_last_error_message(), text) != NULL, "%s", hz_last_error_message());
        bad = good;
        CHECK_OK(hz_session_process(s, &d.frame, &o));
    }
    free(aux);
    free(out);
    free_frame(&f);
    CHECK_OK(hz_session_free(s));
}

/* splitmix64: uniform in (0, 1]. */
static float uniform(uint64_t *state) {
    uint64_t z = (*state += 0x9E3779B97F4A7C15ull);
    z = (z ^ (z >> 30)) * 0xBF58476D1CE4E5B9ull;
    z = (z ^ (z >> 27)) * 0x94D049BB133111EBull;
    z ^= z >> 31;
    return ((float)(z >> 40) + 1.0f) / 16777216.0f;
}

/* A noisy render: each pixel of a lit two-albedo checker times the mean of 4
 * exponential samples (Monte Carlo noise of 4 samples per pixel, deviation
 * half the signal); clean and noisy RGB and the albedo, packed. */
static void noisy_frame(size_t w, size_t h, float *clean, float *noisy, float *albedo) {
    uint64_t rng = 7;
    size_t x, y, k;
    for (y = 0; y < h; y++) {
        for (x = 0; x < w; x++) {
            size_t i = (y * w + x) * 3;
            float tile = (float)((x / 12 + y / 12) % 2);
            float a[3], light = 0.4f + 1.2f * (float)x / (float)w, n = 0.0f;
            a[0] = 0.2f + 0.6f * tile;
            a[1] = 0.5f;
            a[2] = 0.8f - 0.5f * tile;
            for (k = 0; k < 4; k++) n -= logf(uniform(&rng));
            n /= 4.0f;
            for (k = 0; k < 3; k++) {
                albedo[i + k] = a[k];
                clean[i + k] = a[k] * light;
                noisy[i + k] = a[k] * light * n;
            }
        }
    }
}

static double mse_rgb(const float *clean, const float *x, size_t n, size_t x_channels) {
    double sum = 0.0;
    size_t i, k;
    for (i = 0; i < n; i++)
        for (k = 0; k < 3; k++) {
            double e = (double)clean[i * 3 + k] - (double)x[i * x_channels + k];
            sum += e * e;
        }
    return sum / (double)(3 * n);
}

/* denoise on with an albedo: the noisy frame comes out denoised (MSE against
 * the clean frame at least 10 times lower) and the report says so; denoise
 * auto measures the noise and turns itself on. */
static void test_denoise(hz_device *device) {
    size_t w = 96, h = 64, n = w * h;
    float *clean = alloc_floats(n * 3), *noisy = alloc_floats(n * 3), *albedo = alloc_floats(n * 3);
    float *out = alloc_floats(n * 4);
    hz_image c = image(noisy, w, h, 3, 0), a = image(albedo, w, h, 3, 0), o = image(out, w, h, 4, 0);
    hz_frame fr;
    hz_session *s = new_session(device, "bypass"), *autos = new_session(device, "classical");
    hz_status st;
    char decision[256], json[4096];
    noisy_frame(w, h, clean, noisy, albedo);
    memset(&fr, 0, sizeof fr);
    fr.struct_size = sizeof fr;
    fr.color = &c;
    fr.albedo = &a;
    fr.frame_index = 1;
    fr.flags = HZ_FRAME_HAS_INDEX;
    CHECK_OK(hz_session_set_string(s, "denoise", "on"));
    CHECK_OK(hz_session_commit(s));
    st = hz_session_process(s, &fr, &o);
    CHECK(st == HZ_OK,
          "denoise on needs Open Image Denoise: run scripts/setup-venv.sh (it installs pyoidn into .venv) "
          "or set HARMONIZER_OIDN_LIB");
    if (st == HZ_OK) {
        double before = mse_rgb(clean, noisy, n, 3), after = mse_rgb(clean, out, n, 4);
        hz_report r = report_of(s);
        printf("denoise on, albedo: MSE %.5f noisy, %.5f denoised\n", before, after);
        CHECK(after < 0.1 * before, "denoising cuts the error at least tenfold: MSE %g -> %g", before, after);
        CHECK(r.denoised && !r.has_noise_level, "report: denoised %d, has_noise_level %d", r.denoised,
              r.has_noise_level);
        CHECK_OK(hz_session_get_report_denoise_decision(s, decision, sizeof decision, NULL));
        CHECK(strcmp(decision, "denoise on") == 0, "decision: %s", decision);
        CHECK_OK(hz_session_get_report_json(s, json, sizeof json, NULL));
        CHECK(strstr(json, "\"denoised\":true") != NULL && strstr(json, "\"denoise_decision\":\"denoise on\"") != NULL &&
                  strstr(json, "\"noise_level\":null") != NULL,
              "json: %s", json);

        CHECK_OK(hz_session_process(autos, &fr, &o));
        r = report_of(autos);
        CHECK_OK(hz_session_get_report_denoise_decision(autos, decision, sizeof decision, NULL));
        printf("denoise auto: %s\n", decision);
        CHECK(r.denoised && r.has_noise_level && r.noise_level > 0.2f, "auto: denoised %d, noise level %g",
              r.denoised, (double)r.noise_level);
        CHECK(strncmp(decision, "denoise auto: on (noise level", 29) == 0, "decision: %s", decision);
    }
    free(clean);
    free(noisy);
    free(albedo);
    free(out);
    CHECK_OK(hz_session_free(s));
    CHECK_OK(hz_session_free(autos));
}

typedef struct run_seen {
    int frames;
    int preroll;
    int stop_after;
} run_seen;

static bool on_run_frame(void *user, const char *json) {
    run_seen *seen = (run_seen *)user;
    seen->frames++;
    if (strstr(json, "\"preroll\":true") != NULL) seen->preroll++;
    return seen->stop_after == 0 || seen->frames < seen->stop_after;
}

static int file_exists(const char *dir, int frame) {
    char path[4096];
    FILE *f;
    snprintf(path, sizeof path, "%s/o.%04d.exr", dir, frame);
    f = fopen(path, "rb");
    if (f) fclose(f);
    return f != NULL;
}

/* hz_run_sequence: frames 5-8 of an 8-frame sequence with a pre-roll of 3
 * (frames 2-4 processed, not written), the callback sees all 7; a callback
 * returning false cancels; a wrong struct_size, a NULL output and a
 * pre-roll without frames are refused. */
static void test_run_sequence(hz_device *device) {
    const char *input = getenv("HZ_TEST_SEQUENCE");
    const char *dir = getenv("HZ_TEST_OUT");
    char output[4096];
    hz_run_options o;
    run_seen seen;
    hz_session *s = new_session(device, "classical");
    memset(&o, 0, sizeof o);
    o.struct_size = sizeof o;
    o.input = "missing/shot.####.exr";
    o.output = "missing-out/o.####.exr";
    o.flags = HZ_RUN_HAS_FRAMES;
    o.frame_first = 5;
    o.frame_last = 8;
    o.struct_size = sizeof o - 1;
    CHECK(hz_run_sequence(s, &o, NULL, NULL) == HZ_ERROR_INVALID_ARGUMENT, "run: wrong struct_size refused");
    CHECK(strstr(hz_last_error_message(), "hz_run_options.struct_size") != NULL, "run: %s", hz_last_error_message());
    o.struct_size = sizeof o;
    o.output = NULL;
    CHECK(hz_run_sequence(s, &o, NULL, NULL) == HZ_ERROR_INVALID_ARGUMENT, "run: NULL output refused");
    CHECK(strstr(hz_last_error_message(), "options.output is NULL") != NULL, "run: %s", hz_last_error_message());
    o.flags = 0;
    o.preroll = 3;
    o.output = "missing-out/o.####.exr";
    CHECK(hz_run_sequence(s, &o, NULL, NULL) == HZ_ERROR_INVALID_ARGUMENT, "run: pre-roll without frames refused");
    CHECK(strstr(hz_last_error_message(), "--preroll needs --frames") != NULL, "run: %s", hz_last_error_message());
    if (!input || !dir) {
        printf("test_run_sequence: HZ_TEST_SEQUENCE/HZ_TEST_OUT not set (make writes them with harmonize synth): "
               "ONLY THE REFUSALS WERE CHECKED\n");
        CHECK_OK(hz_session_free(s));
        return;
    }
    snprintf(output, sizeof output, "%s/o.####.exr", dir);
    o.input = input;
    o.output = output;
    o.flags = HZ_RUN_HAS_FRAMES;
    memset(&seen, 0, sizeof seen);
    CHECK_OK(hz_run_sequence(s, &o, on_run_frame, &seen));
    CHECK(seen.frames == 7 && seen.preroll == 3, "run: %d frames, %d pre-roll", seen.frames, seen.preroll);
    CHECK(!file_exists(dir, 4) && file_exists(dir, 5) && file_exists(dir, 8), "run: only frames 5-8 written");
    CHECK(report_of(s).frame_index == 8, "run: the session's report is frame 8's");
    CHECK_OK(hz_session_reset(s));
    memset(&seen, 0, sizeof seen);
    seen.stop_after = 1;
    o.preroll = 0;
    o.frame_first = 1;
    CHECK(hz_run_sequence(s, &o, on_run_frame, &seen) == HZ_ERROR_CANCELLED, "run: the callback cancels");
    CHECK(seen.frames == 1 && file_exists(dir, 1) && !file_exists(dir, 2), "run: stopped after frame 1");
    CHECK_OK(hz_session_free(s));
}

int main(void) {
    hz_device *device = NULL;
    hz_device_options opts;
    memset(&opts, 0, sizeof opts);
    opts.struct_size = sizeof opts;
    opts.threads = 2;
    test_version();
    CHECK_OK(hz_device_new(HZ_VERSION_MAJOR, &opts, &device));
    if (!device) return 1;
    {
        uint32_t threads = 0;
        CHECK_OK(hz_device_get_threads(device, &threads));
        CHECK(threads == 2, "threads %u", threads);
    }
    test_sequence(device);
    test_default_backend(device);
    test_in_place_strided(device);
    test_nan_inf(device);
    test_bad_arguments(device);
    test_resize(device);
    test_cancel(device);
    test_reentry(device);
    test_threads(device);
    test_too_large(device);
    test_index_wrap(device);
    test_settings_and_models(device);
    test_normals(device);
    test_older_struct_sizes(device);
    test_albedo_validated(device);
    test_insert_id(device);
    test_denoise(device);
    test_run_sequence(device);
    CHECK_OK(hz_device_free(device));
    printf("%s: %d checks, %d failures\n", failures ? "FAILED" : "ok", checks, failures);
    return failures ? 1 : 0;
}
