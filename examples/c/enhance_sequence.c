/*
 * enhance_sequence.c: a minimal renderer host of libharmonizer.
 *
 * A renderer hands the library each finished frame: its RGBA beauty buffer
 * (scene-linear Linear Rec.709, premultiplied; alpha = coverage), planar
 * depth and motion vectors (pixels, current -> previous, x right, y down).
 * The library enhances the RGB of the beauty buffer in place, keeping the
 * last frames as temporal context. Here a small procedural "renderer" stands
 * in for yours: a scrolling texture with a hole the renderer left empty.
 *
 * Build (after scripts/build-ffi.sh):
 *   cc -std=c99 enhance_sequence.c $(pkg-config --cflags --libs harmonizer) -lm -o enhance_sequence
 * Run:
 *   ./enhance_sequence [frames] [width] [height] [output_dir]
 * With output_dir, input and output frames are written as PFM images
 * (linear float RGB; open them with any image viewer that reads PFM).
 */
#include <harmonizer.h>

#include <math.h>
#include <stdio.h>
#include <stdlib.h>
#include <string.h>

/* Prints the library's message for a failed call and exits. */
static void check(hz_status status, const char *what) {
    if (status != HZ_OK) {
        fprintf(stderr, "%s failed: %s: %s\n", what, hz_status_name(status), hz_last_error_message());
        exit(1);
    }
}

/* Warnings from the library (NaN color, frame gaps, ...). */
static void on_message(void *user, uint32_t level, const char *text) {
    (void)user;
    fprintf(stderr, "harmonizer %s: %s\n", level == HZ_MESSAGE_WARNING ? "warning" : "info", text);
}

/* The stand-in renderer: fills RGBA, depth and motion for frame t. */
static void render(int t, size_t w, size_t h, float *rgba, float *depth, float *motion) {
    size_t x, y;
    for (y = 0; y < h; y++) {
        for (x = 0; x < w; x++) {
            size_t i = y * w + x;
            double u = ((double)x - 2.0 * t) / 16.0, v = (double)y / 16.0;
            int hole = x > w / 3 && x < w / 2 && y > h / 3 && y < h / 2; /* no samples here */
            float a = hole ? 0.0f : 1.0f;
            float flicker = 1.0f + 0.05f * (float)(t % 3); /* the noise we want gone */
            rgba[i * 4 + 0] = a * flicker * (float)(0.5 + 0.4 * sin(u));
            rgba[i * 4 + 1] = a * flicker * (float)(0.5 + 0.4 * cos(v));
            rgba[i * 4 + 2] = a * flicker * 0.3f;
            rgba[i * 4 + 3] = a;
            depth[i] = hole ? 1e10f : 10.0f;
            motion[i * 2 + 0] = -2.0f; /* the surface was 2 px to the left last frame */
            motion[i * 2 + 1] = 0.0f;
        }
    }
}

/* Writes the RGB of an RGBA buffer as a PFM file (bottom row first). */
static void write_pfm(const char *path, const float *rgba, size_t w, size_t h) {
    FILE *f = fopen(path, "wb");
    size_t x, y;
    if (!f) {
        perror(path);
        exit(1);
    }
    fprintf(f, "PF\n%zu %zu\n-1.0\n", w, h);
    for (y = h; y-- > 0;) {
        for (x = 0; x < w; x++) fwrite(&rgba[(y * w + x) * 4], sizeof(float), 3, f);
    }
    fclose(f);
}

int main(int argc, char **argv) {
    int frames = argc > 1 ? atoi(argv[1]) : 24;
    size_t w = argc > 2 ? (size_t)atol(argv[2]) : 320, h = argc > 3 ? (size_t)atol(argv[3]) : 180;
    const char *out_dir = argc > 4 ? argv[4] : NULL;
    float *rgba = (float *)malloc(w * h * 4 * sizeof(float));
    float *depth = (float *)malloc(w * h * sizeof(float));
    float *motion = (float *)malloc(w * h * 2 * sizeof(float));
    hz_device_options options;
    hz_device *device = NULL;
    hz_session *session = NULL;
    hz_image color, depth_image, motion_image, coverage;
    hz_frame frame;
    char path[4096], backend[32];
    int t;
    if (!rgba || !depth || !motion || frames <= 0 || w == 0 || h == 0) {
        fprintf(stderr, "usage: %s [frames] [width] [height] [output_dir]\n", argv[0]);
        return 2;
    }

    /* One device per process (its thread pool is shared by sessions); one
     * session per camera. Pass the header's major version. */
    memset(&options, 0, sizeof options);
    options.struct_size = sizeof options;
    check(hz_device_new(HZ_VERSION_MAJOR, &options, &device), "hz_device_new");
    check(hz_session_new(device, &session), "hz_session_new");
    /* Parameters by name, then commit. "auto" uses the neural model when the
     * library has one, else the classical pipeline. */
    check(hz_session_set_string(session, "backend", "auto"), "backend");
    check(hz_session_set_int(session, "context_frames", 4), "context_frames");
    check(hz_session_commit(session), "hz_session_commit");
    check(hz_session_set_message_callback(session, on_message, NULL), "message callback");
    check(hz_session_get_backend_name(session, backend, sizeof backend, NULL), "backend name");
    printf("libharmonizer %s, backend %s, %dx%d, %d frames\n", hz_version(), backend, (int)w, (int)h, frames);

    /* Describe the renderer's buffers once: they are read (and the RGB
     * written) in place, without copies. */
    memset(&color, 0, sizeof color);
    color.struct_size = sizeof color;
    color.format = HZ_FORMAT_F32;
    color.width = w;
    color.height = h;
    color.data = rgba;
    color.channels = 3;      /* RGB is color ... */
    color.pixel_stride = 16; /* ... inside RGBA pixels */
    coverage = color;        /* alpha of the same buffer is the coverage */
    coverage.channels = 1;
    coverage.offset = 3 * sizeof(float);
    depth_image = color;
    depth_image.channels = 1;
    depth_image.pixel_stride = 0; /* packed */
    depth_image.data = depth;
    motion_image = depth_image;
    motion_image.channels = 2;
    motion_image.data = motion;

    for (t = 0; t < frames; t++) {
        hz_report report;
        render(t, w, h, rgba, depth, motion);
        if (out_dir) {
            snprintf(path, sizeof path, "%s/input_%04d.pfm", out_dir, t);
            write_pfm(path, rgba, w, h);
        }
        memset(&frame, 0, sizeof frame);
        frame.struct_size = sizeof frame;
        frame.color = &color;
        frame.coverage = &coverage;
        frame.depth = &depth_image;
        frame.motion = &motion_image;
        frame.frame_index = t;
        frame.flags = HZ_FRAME_HAS_INDEX; /* a camera cut would add HZ_FRAME_RESET */
        frame.motion_vector_scale[0] = 1.0f;
        frame.motion_vector_scale[1] = 1.0f; /* -1 for a +y-up renderer such as Blender */
        /* In place: the output is the RGB of the beauty buffer itself. */
        check(hz_session_process(session, &frame, &color), "hz_session_process");

        memset(&report, 0, sizeof report);
        report.struct_size = sizeof report;
        check(hz_session_get_report(session, &report), "hz_session_get_report");
        printf("frame %4d: %6.2f ms, history %zu%s\n", t, report.total_ms, report.history_used,
               report.reset_reason != HZ_RESET_NONE ? " (reset)" : "");
        if (out_dir) {
            snprintf(path, sizeof path, "%s/output_%04d.pfm", out_dir, t);
            write_pfm(path, rgba, w, h);
        }
    }

    check(hz_session_free(session), "hz_session_free");
    check(hz_device_free(device), "hz_device_free");
    free(rgba);
    free(depth);
    free(motion);
    return 0;
}
