"""Renders a trained drape run through the C ABI with ctypes (no other dependency).

    python3 examples/python/render_avatar.py target/debug/libdrape.so RUN_DIR OUT.rgba32f

Writes the run's first held-out frame as "W H\\n" and raw little-endian floats (width x
height x 4, sRGB-encoded premultiplied RGBA, top row first), as examples/c/render_avatar.c does.
"""
import ctypes
import sys


class Camera(ctypes.Structure):
    # drape_camera: fx, fy, cx, cy, world_to_camera[16] (row-major), z_near, z_far.
    _fields_ = [("fx", ctypes.c_float), ("fy", ctypes.c_float), ("cx", ctypes.c_float), ("cy", ctypes.c_float),
                ("world_to_camera", ctypes.c_float * 16), ("z_near", ctypes.c_float), ("z_far", ctypes.c_float)]


def main(lib_path, run_dir, out_path):
    lib = ctypes.CDLL(lib_path)
    lib.drape_last_error.restype = ctypes.c_char_p
    lib.drape_context_create.restype = ctypes.c_void_p
    lib.drape_context_create.argtypes = [ctypes.c_void_p]
    lib.drape_avatar_load.restype = ctypes.c_void_p
    lib.drape_avatar_load.argtypes = [ctypes.c_void_p, ctypes.c_char_p, ctypes.c_void_p, ctypes.c_void_p]
    lib.drape_avatar_default_view.argtypes = [ctypes.c_void_p, ctypes.POINTER(Camera), ctypes.POINTER(ctypes.c_uint32),
                                              ctypes.POINTER(ctypes.c_uint32), ctypes.POINTER(ctypes.c_float), ctypes.POINTER(ctypes.c_float)]
    lib.drape_avatar_set_pose.argtypes = [ctypes.c_void_p, ctypes.POINTER(ctypes.c_float), ctypes.POINTER(ctypes.c_float)]
    lib.drape_avatar_render.argtypes = [ctypes.c_void_p, ctypes.POINTER(Camera), ctypes.c_uint32, ctypes.c_uint32, ctypes.POINTER(ctypes.c_float), ctypes.c_size_t]
    lib.drape_avatar_destroy.argtypes = [ctypes.c_void_p]
    lib.drape_context_destroy.argtypes = [ctypes.c_void_p]

    def check(status, what):
        if status != 0:
            sys.exit(f"render_avatar.py: {what}: status {status}: {lib.drape_last_error().decode()}")

    ctx = lib.drape_context_create(None)
    if not ctx:
        sys.exit(f"render_avatar.py: {lib.drape_last_error().decode()}")
    avatar = lib.drape_avatar_load(ctx, run_dir.encode(), None, None)
    if not avatar:
        sys.exit(f"render_avatar.py: {lib.drape_last_error().decode()}")
    camera, width, height = Camera(), ctypes.c_uint32(), ctypes.c_uint32()
    pose, translation = (ctypes.c_float * 72)(), (ctypes.c_float * 3)()
    check(lib.drape_avatar_default_view(avatar, ctypes.byref(camera), ctypes.byref(width), ctypes.byref(height), pose, translation), "default view")
    check(lib.drape_avatar_set_pose(avatar, pose, translation), "set pose")
    floats = width.value * height.value * 4
    rgba = (ctypes.c_float * floats)()
    check(lib.drape_avatar_render(avatar, ctypes.byref(camera), width, height, rgba, floats), "render")
    with open(out_path, "wb") as f:
        f.write(f"{width.value} {height.value}\n".encode())
        f.write(bytes(rgba))
    check(lib.drape_avatar_destroy(avatar), "destroy avatar")
    check(lib.drape_context_destroy(ctx), "destroy context")
    print(f"rendered {width.value}x{height.value}")


if __name__ == "__main__":
    if len(sys.argv) != 4:
        sys.exit(__doc__)
    main(*sys.argv[1:])
