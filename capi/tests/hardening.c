/* The C ABI's hardening, as a C caller sees it (compiled and run by capi/tests/capi.rs,
 * with -Dnear= -Dfar= as <windows.h> defines them, against a libdrape.so built with the
 * test-only `testing` feature):
 *   - drape_version() and drape_status_str();
 *   - a 1x1 image asked for with a 3-float buffer is DRAPE_ERROR_INVALID_ARGUMENT, and
 *     nothing is written;
 *   - frames in flight out of range are refused at load;
 *   - a panic inside a call on an avatar retires it: later calls are
 *     DRAPE_ERROR_INVALID_HANDLE with a message saying so, and it can still be destroyed;
 *     another avatar is unaffected.
 *
 *   hardening RUN_DIR   (exit status 0 and "ok" when every check holds)
 */
#include <stdio.h>
#include <string.h>

#include "drape.h"

/* The test-only hook (the `testing` feature; not in the header). */
drape_status drape_testing_panic_in_avatar_call(drape_avatar *avatar);

static int failed(const char *what) {
    fprintf(stderr, "hardening: %s (last error: %s)\n", what, drape_last_error());
    return 1;
}

#define CHECK(cond, what)                                                                          \
    do {                                                                                           \
        if (!(cond)) return failed(what);                                                          \
    } while (0)

int main(int argc, char **argv) {
    if (argc != 2) {
        fprintf(stderr, "usage: %s RUN_DIR\n", argv[0]);
        return 2;
    }
    const char *version = drape_version();
    CHECK(version && strlen(version) >= 5 && strchr(version, '.'), "drape_version");
    CHECK(strstr(drape_status_str(DRAPE_ERROR_INVALID_HANDLE), "INVALID_HANDLE") != NULL, "drape_status_str");
    CHECK(strstr(drape_status_str(DRAPE_ERROR_OUT_OF_MEMORY), "OUT_OF_MEMORY") != NULL, "drape_status_str (memory)");
    CHECK(strcmp(drape_status_str(1000), "unknown status") == 0, "drape_status_str (unknown)");

    drape_context *ctx = drape_context_create(NULL);
    CHECK(ctx, "drape_context_create");

    drape_load_options too_many = {0};
    too_many.frames_in_flight = 9;
    drape_status status = DRAPE_OK;
    CHECK(!drape_avatar_load(ctx, argv[1], &too_many, &status), "9 frames in flight loaded");
    CHECK(status == DRAPE_ERROR_INVALID_ARGUMENT, "9 frames in flight: the status");
    CHECK(strstr(drape_last_error(), "frames_in_flight"), "9 frames in flight: the message");

    drape_load_options options = {0};
    options.frames_in_flight = 1;
    drape_avatar *avatar = drape_avatar_load(ctx, argv[1], &options, &status);
    CHECK(avatar && status == DRAPE_OK, "drape_avatar_load");
    drape_avatar *other = drape_avatar_load(ctx, argv[1], NULL, NULL);
    CHECK(other, "drape_avatar_load (the other avatar)");

    drape_camera camera;
    uint32_t width = 0, height = 0;
    float pose[72], translation[3];
    CHECK(drape_avatar_default_view(avatar, &camera, &width, &height, pose, translation) == DRAPE_OK,
          "drape_avatar_default_view");
    CHECK(camera.z_near > 0.0f && camera.z_far > camera.z_near, "z_near, z_far");

    /* A 1x1 image needs 4 floats: with room for 3, nothing is written. */
    float canary[4] = {-7.0f, -7.0f, -7.0f, -7.0f};
    CHECK(drape_avatar_render(avatar, &camera, 1, 1, canary, 3) == DRAPE_ERROR_INVALID_ARGUMENT,
          "a 1x1 image into 3 floats");
    CHECK(strstr(drape_last_error(), "rgba_len"), "a 1x1 image into 3 floats: the message");
    for (int i = 0; i < 4; i++) CHECK(canary[i] == -7.0f, "a 1x1 image into 3 floats wrote");
    CHECK(drape_avatar_render(avatar, &camera, 1, 1, canary, 4) == DRAPE_OK, "a 1x1 image into 4 floats");
    CHECK(canary[3] >= 0.0f && canary[3] <= 1.0f, "a 1x1 image's alpha");

    /* A panic inside a call retires the avatar. */
    CHECK(drape_testing_panic_in_avatar_call(avatar) == DRAPE_ERROR_PANIC, "the panic's status");
    CHECK(strstr(drape_last_error(), "a deliberate panic"), "the panic's message");
    CHECK(drape_avatar_set_pose(avatar, pose, translation) == DRAPE_ERROR_INVALID_HANDLE,
          "a call on the retired avatar");
    CHECK(strstr(drape_last_error(), "retired after a panic"), "the retired avatar's message");
    CHECK(drape_avatar_render(avatar, &camera, 1, 1, canary, 4) == DRAPE_ERROR_INVALID_HANDLE,
          "a render of the retired avatar");
    CHECK(drape_avatar_default_view(other, &camera, &width, &height, NULL, NULL) == DRAPE_OK,
          "the other avatar after the panic");
    CHECK(drape_avatar_render(other, &camera, 1, 1, canary, 4) == DRAPE_OK, "the other avatar's render");
    CHECK(drape_avatar_destroy(avatar) == DRAPE_OK, "destroying the retired avatar");
    CHECK(drape_avatar_destroy(avatar) == DRAPE_ERROR_INVALID_HANDLE, "destroying it twice");
    CHECK(drape_avatar_destroy(other) == DRAPE_OK, "destroying the other avatar");
    CHECK(drape_context_destroy(ctx) == DRAPE_OK, "drape_context_destroy");
    printf("ok (drape %s)\n", version);
    return 0;
}
