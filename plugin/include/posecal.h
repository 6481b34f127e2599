/*
 * posecal.h - C ABI of libposecal.so, camera calibration with efficient pose selection.
 *
 * Conventions (see docs/c-api.md):
 *  - Plain C99; compiles as C and C++. Every symbol starts with posecal_ / POSECAL_.
 *  - Opaque handles. Every create has a destroy that accepts NULL.
 *  - Every function returns a posecal_status (or a value that cannot fail). On failure,
 *    posecal_last_error() returns the message of the last failure on the calling thread.
 *    No C++ exception ever crosses this interface.
 *  - Strings are UTF-8, NUL-terminated. JSON-returning calls: *size is the buffer's capacity on
 *    entry; on return it holds the length needed including the terminating NUL. A NULL or too
 *    small buffer gives POSECAL_E_BUFFER_TOO_SMALL with *size set (nothing else changes).
 *  - Threads: different handles may be used on different threads concurrently. One handle is
 *    not to be used from two threads at the same time unless a function says otherwise.
 *  - Blocking: a call blocks at most as long as its timeout argument says, or as its
 *    documentation says; nothing waits forever.
 *  - Board frame: that of OpenCV 4.6's CharucoBoard object points (origin at the board's
 *    top-left corner, x along the columns, y down the rows, z into the board), metres.
 */
#ifndef POSECAL_H
#define POSECAL_H

#include <stddef.h>
#include <stdint.h>

#if defined(_WIN32)
#if defined(POSECAL_BUILDING)
#define POSECAL_API __declspec(dllexport)
#else
#define POSECAL_API __declspec(dllimport)
#endif
#else
#define POSECAL_API __attribute__((visibility("default")))
#endif

#ifdef __cplusplus
#define POSECAL_NOEXCEPT noexcept
extern "C" {
#else
#define POSECAL_NOEXCEPT
#endif

/* ABI version: incremented on any incompatible change of this header's types or functions. */
#define POSECAL_ABI_VERSION 1u

typedef enum posecal_status {
  POSECAL_OK = 0,
  POSECAL_E_INVALID_ARGUMENT = 1, /* NULL where not allowed, malformed JSON/spec, bad value */
  POSECAL_E_NOT_FOUND = 2,        /* camera, file, feature or JSON key that does not exist */
  POSECAL_E_BUFFER_TOO_SMALL = 3, /* *size says how much is needed */
  POSECAL_E_TIMEOUT = 4,          /* no frame within the timeout */
  POSECAL_E_DEVICE = 5,           /* camera failed or disconnected */
  POSECAL_E_STATE = 6,            /* call not allowed in the current state */
  POSECAL_E_IO = 7,               /* file could not be read or written */
  POSECAL_E_INTERNAL = 8,         /* a bug in posecal: please report the message */
  POSECAL_E_DEGENERATE = 9,       /* the data cannot determine the calibration */
  POSECAL_E_UNSUPPORTED = 10      /* valid request this build or camera cannot do */
} posecal_status;

/* Returns POSECAL_ABI_VERSION of the library (compare with the header's). */
POSECAL_API unsigned posecal_abi_version(void) POSECAL_NOEXCEPT;
/* Library version, e.g. "0.1.0". Static storage. */
POSECAL_API const char* posecal_version(void) POSECAL_NOEXCEPT;
/* Message of the last failure on the calling thread ("" if none). Valid until the next posecal
 * call on this thread. */
POSECAL_API const char* posecal_last_error(void) POSECAL_NOEXCEPT;
/* Name of a status code, e.g. "POSECAL_E_TIMEOUT". Static storage. */
POSECAL_API const char* posecal_status_name(posecal_status status) POSECAL_NOEXCEPT;

/* ---- Context: camera backends and defaults, shared by sessions ---------------------------- */
typedef struct posecal_context posecal_context;

/* options_json: NULL for defaults, or an object with optional keys
 *   "backends": ["sim", "images", "external", "aravis", "v4l2"]   (which to enable)
 * An unknown key is POSECAL_E_INVALID_ARGUMENT. */
POSECAL_API posecal_status posecal_context_create(const char* options_json,
                                                  posecal_context** out) POSECAL_NOEXCEPT;
POSECAL_API void posecal_context_destroy(posecal_context* ctx) POSECAL_NOEXCEPT;

/* JSON array of every camera of every enabled backend: objects with "uri", "backend", "id",
 * "vendor", "model", "serial", "transport". May block up to ~1 s while backends scan. */
POSECAL_API posecal_status posecal_list_cameras(posecal_context* ctx, char* buf,
                                                size_t* size) POSECAL_NOEXCEPT;

/* ---- Printable targets -------------------------------------------------------------------- */
/* Writes the target (spec like "charuco:9x6:0.028:0.0182:DICT_4X4_50"; NULL = default) at exact
 * physical scale: vector PDF or PNG at `dpi`, chosen by the extension of `path`. */
POSECAL_API posecal_status posecal_write_target(const char* target_spec, const char* path,
                                                double dpi, double margin_m) POSECAL_NOEXCEPT;

/* ---- Offline calibration from a folder of images ------------------------------------------ */
typedef struct posecal_calibration posecal_calibration;

/* Calibrates from every image of `images_dir` (name order). options_json: NULL or an object
 * with optional keys "fix_principal_point", "fix_aspect_ratio", "zero_tangential" (bool),
 * "fixed" (array of parameter names), "min_corners" (int). Unreadable images and images without
 * the target are listed in the result, not fatal. Blocks for the whole calibration. */
POSECAL_API posecal_status posecal_calibrate_images(posecal_context* ctx, const char* images_dir,
                                                    const char* target_spec,
                                                    const char* options_json,
                                                    posecal_calibration** out) POSECAL_NOEXCEPT;
/* Result JSON: "fx" ... "k3", "std" (object, sigma scaled by the residual variance),
 * "std_unit" (sigma at 1 px noise, paper eq. 5), "rms", "frames_used", "frames_rejected",
 * "used", "rejected", "per_frame_rms", "covariance" (intrinsics block, scaled), ... */
POSECAL_API posecal_status posecal_calibration_json(const posecal_calibration* cal, char* buf,
                                                    size_t* size) POSECAL_NOEXCEPT;
/* Writes OpenCV YAML (.yml/.yaml) or JSON (.json) in cv::FileStorage format. */
POSECAL_API posecal_status posecal_calibration_save(const posecal_calibration* cal,
                                                    const char* path) POSECAL_NOEXCEPT;
POSECAL_API void posecal_calibration_destroy(posecal_calibration* cal) POSECAL_NOEXCEPT;

/* ---- Calibration sessions: one camera, one pose-selection engine --------------------------- */
typedef struct posecal_session posecal_session;

typedef enum posecal_pixel_format {
  POSECAL_PIXEL_MONO8 = 0,
  POSECAL_PIXEL_BGR8 = 1,
  POSECAL_PIXEL_RGB8 = 2
} posecal_pixel_format;

/* A host image. struct_size = sizeof(posecal_image), set by the caller, so the struct can grow
 * in later ABI versions. The library never keeps `data` beyond the call. */
typedef struct posecal_image {
  uint32_t struct_size;
  int32_t width;
  int32_t height;
  int32_t stride_bytes;
  int32_t format; /* posecal_pixel_format */
  void* data;
} posecal_image;

/* Opens a session on a camera (URI as listed by posecal_list_cameras, or "sim://?...",
 * "images://DIR", "external"). config_json: NULL for defaults, or an object with optional keys
 *   "target": spec string (default "charuco:9x6:0.028:0.0182:DICT_4X4_50"),
 *   "operator": "person" | "robot"   (robot: the host reports poses reached),
 *   "convergence_threshold" (0.1), "max_keyframes" (20), "jaccard_threshold" (0.8),
 *   "still_motion_px" (1.5), "constraint_factor" (5), "target_timeout_frames" (0 = never),
 *   "pose_candidates" (int), "lock_settings" (true), "max_tilt_deg" (70)
 * An unknown key is POSECAL_E_INVALID_ARGUMENT. Opening a camera may block up to ~3 s. */
POSECAL_API posecal_status posecal_session_open(posecal_context* ctx, const char* camera_uri,
                                                const char* config_json,
                                                posecal_session** out) POSECAL_NOEXCEPT;
/* Stops the camera and frees the session. NULL-tolerant. Must not be called from the session's
 * own event callback. */
POSECAL_API void posecal_session_close(posecal_session* session) POSECAL_NOEXCEPT;

/* Takes one frame from the session's camera (waiting at most timeout_ms) and advances the state
 * machine. POSECAL_OK: a frame was processed. POSECAL_E_TIMEOUT: no frame in time.
 * POSECAL_E_DEVICE: the camera is disconnected (keyframes are kept; keep stepping to resume when
 * it is back). POSECAL_E_STATE: the calibration has finished, or an "external" session (use
 * posecal_session_feed). POSECAL_E_NOT_FOUND: a finite source (images://) has no more frames. */
POSECAL_API posecal_status posecal_session_step(posecal_session* session,
                                                int timeout_ms) POSECAL_NOEXCEPT;
/* Processes a host frame synchronously (the state machine has advanced when it returns). For
 * any session; "external" sessions get frames only this way. */
POSECAL_API posecal_status posecal_session_feed(posecal_session* session,
                                                const posecal_image* image) POSECAL_NOEXCEPT;

/* Current status JSON: "state", "converged", "keyframes", "target_parameter", "guidance",
 * "jaccard", "still", "board_visible", "corners", "image_width", "image_height", "frames",
 * "camera", "parameters": {"fx": {"value", "std", "converged"}, ...}. */
POSECAL_API posecal_status posecal_session_status(posecal_session* session, char* buf,
                                                  size_t* size) POSECAL_NOEXCEPT;
/* The board pose to reach: rotation vector and translation (metres) of the board frame in the
 * camera frame. POSECAL_E_STATE when there is no target (before the first frame, or finished). */
POSECAL_API posecal_status posecal_session_target_pose(posecal_session* session, double rvec[3],
                                                       double tvec[3]) POSECAL_NOEXCEPT;
/* Robot mode: the robot has reached the current target; the session captures as soon as the
 * board is seen and still (the Jaccard check does not gate a robot's capture). */
POSECAL_API posecal_status posecal_session_pose_reached(posecal_session* session) POSECAL_NOEXCEPT;
/* Draws the guidance overlay (target board, detected corners, text) into a host image of the
 * camera's size, in place. */
POSECAL_API posecal_status posecal_session_render_overlay(posecal_session* session,
                                                          posecal_image* inout) POSECAL_NOEXCEPT;
/* Result JSON: "converged", model values, "std", "std_unit", "covariance", "eps_res",
 * "keyframes", "camera" identity, "locked_settings", "started"/"finished" timestamps; for
 * sim:// cameras also "eps_test", "eps_gt" and the ground truth. POSECAL_E_STATE before the
 * second keyframe (no calibration yet). */
POSECAL_API posecal_status posecal_session_result(posecal_session* session, char* buf,
                                                  size_t* size) POSECAL_NOEXCEPT;
/* Saves the calibration: OpenCV YAML (.yml/.yaml) or JSON (.json) by extension. */
POSECAL_API posecal_status posecal_session_save(posecal_session* session,
                                                const char* path) POSECAL_NOEXCEPT;

/* Events: called with a kind ("state_changed", "captured", "keyframe_rejected", "calibrated",
 * "parameter_converged", "target_changed", "target_skipped", "camera_disconnected",
 * "camera_reconnected", "error") and a JSON payload, on every state change, capture and error.
 * Called on the thread that is inside posecal_session_step/feed, before that call returns.
 * Inside the callback only posecal_session_status, posecal_session_target_pose and
 * posecal_last_error may be called on the same session. The strings are valid only during the
 * call. fn = NULL removes the callback. */
typedef void (*posecal_event_fn)(void* user_data, const char* kind, const char* payload_json);
POSECAL_API posecal_status posecal_session_set_callback(posecal_session* session,
                                                        posecal_event_fn fn,
                                                        void* user_data) POSECAL_NOEXCEPT;

#ifdef __cplusplus
}
#endif

#endif /* POSECAL_H */
