/* Renders a trained drape run through the C ABI: the run's first held-out frame's pose
 * and camera, written as raw little-endian floats (width x height x 4, sRGB-encoded
 * premultiplied RGBA, top row first) after a one-line text header "W H\n".
 *
 *   cc -I capi/include examples/c/render_avatar.c -L target/debug -ldrape -o render_avatar
 *   ./render_avatar RUN_DIR OUT.rgba32f
 */
#include <stdio.h>
#include <stdlib.h>

#include "drape.h"

static int fail(const char *what) {
    fprintf(stderr, "render_avatar: %s: %s\n", what, drape_last_error());
    return 1;
}

int main(int argc, char **argv) {
    if (argc != 3) {
        fprintf(stderr, "usage: %s RUN_DIR OUT.rgba32f\n", argv[0]);
        return 2;
    }
    drape_context *ctx = drape_context_create(NULL);
    if (!ctx) return fail("drape_context_create");
    drape_avatar *avatar = drape_avatar_load(ctx, argv[1], NULL, NULL);
    if (!avatar) return fail("drape_avatar_load");

    drape_camera camera;
    uint32_t width = 0, height = 0;
    float pose[72], translation[3];
    if (drape_avatar_default_view(avatar, &camera, &width, &height, pose, translation) != DRAPE_OK)
        return fail("drape_avatar_default_view");
    if (drape_avatar_set_pose(avatar, pose, translation) != DRAPE_OK) return fail("drape_avatar_set_pose");

    size_t floats = (size_t)width * height * 4;
    float *rgba = malloc(floats * sizeof(float));
    if (!rgba) return 1;
    if (drape_avatar_render(avatar, &camera, width, height, rgba, floats) != DRAPE_OK) return fail("drape_avatar_render");

    FILE *out = fopen(argv[2], "wb");
    if (!out) {
        perror(argv[2]);
        return 1;
    }
    fprintf(out, "%u %u\n", width, height);
    fwrite(rgba, sizeof(float), floats, out);
    fclose(out);
    free(rgba);

    /* A destroyed handle is an error status, not a crash. */
    if (drape_avatar_destroy(avatar) != DRAPE_OK) return fail("drape_avatar_destroy");
    if (drape_avatar_destroy(avatar) != DRAPE_ERROR_INVALID_HANDLE) return fail("second destroy");
    if (drape_context_destroy(ctx) != DRAPE_OK) return fail("drape_context_destroy");
    printf("rendered %ux%u\n", width, height);
    return 0;
}
