/*
 * posecal.h - C ABI of libposecal.so, camera calibration with efficient pose selection.
 *
 * Conventions (docs/c-api.md has the details, the JSON schemas and a complete example):
 *  - Plain C99; compiles as C and C++. Every symbol starts with posecal_ / POSECAL_; the library
 *    exports nothing else.
 *  - Opaque handles. Every create/open has a destroy/close that accepts NULL. A handle belongs to
 *    the caller from the create until the destroy; the library keeps no pointer to caller memory
 *    beyond a call (callback user_data excepted, until the callback is replaced or the session
 *    closed). Strings the library returns are in static storage or valid until the next posecal
 *    call on the same thread, as each function says.
 *  - Every function returns a posecal_status (or a value that cannot fail). On failure,
 *    posecal_last_error() returns a non-empty message for the last failure on the calling thread.
 *    No C++ exception ever crosses this interface: every entry point is noexcept.
 *  - NULL where a handle or pointer is required: POSECAL_E_INVALID_ARGUMENT naming the argument.
 *    Output handles (`out`) are set to NULL first, so they are NULL after any failure.
 *  - Strings are UTF-8, NUL-terminated. JSON-returning calls: *size is the buffer's capacity on
 *    entry; on return it holds the length needed including the terminating NUL. A NULL or too
 *    small buffer gives POSECAL_E_BUFFER_TOO_SMALL with *size set and the buffer untouched.
 *    Calls that do work once (list, features, grab, evaluate) keep their JSON when the buffer is
 *    too small: the next call of the same function with the same arguments on the same thread
 *    and context returns it without doing the work again.
 *  - JSON options/configs: NULL or "" for defaults, else an object. An unknown key, a wrong type
 *    or a value out of range is POSECAL_E_INVALID_ARGUMENT naming the key.
 *  - Threads: a posecal_context is thread-safe: its functions may be called from several threads
 *    at once, and sessions opened on it may run concurrently, each on its own thread. A session
 *    (and a posecal_calibration) is used by one thread at a time: it may move between threads,
 *    but two calls on the same session must never overlap. A context may be destroyed while
 *    sessions opened on it are open: they keep what they need until they are closed.
 *  - Blocking: no call waits forever. Calls that wait for a camera take a timeout; the others
 *    compute, and their documentation says for how long they typically run.
 *  - Board frame: that of OpenCV 4.6's CharucoBoard object points (origin at the board's
 *    top-left corner, x along the columns, y down the rows, z into the board), metres.
 *  - Versioning: POSECAL_ABI_VERSION changes on any incompatible change of this header; new
 *    functions may be added within a version. Struct layouts are frozen (posecal_image may only
 *    grow at its end: hosts set struct_size).
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
  POSECAL_E_NOT_FOUND = 2,        /* camera, file, feature or frame that does not exist */
  POSECAL_E_BUFFER_TOO_SMALL = 3, /* *size says how much is needed */
  POSECAL_E_TIMEOUT = 4,          /* no frame within the timeout */
  POSECAL_E_DEVICE = 5,           /* camera failed or disconnected */
  POSECAL_E_STATE = 6,            /* call not allowed in the current state */
  POSECAL_E_IO = 7,               /* file could not be read or written */
  POSECAL_E_INTERNAL = 8,         /* a bug in posecal: please report the message */
  POSECAL_E_DEGENERATE = 9,       /* the data cannot determine the calibration */
  POSECAL_E_UNSUPPORTED = 10      /* valid request this build, context or camera cannot do */
} posecal_status;

/* Returns POSECAL_ABI_VERSION of the library (compare with the header's). Any thread. */
POSECAL_API unsigned posecal_abi_version(void) POSECAL_NOEXCEPT;
/* Library version, e.g. "0.1.0". Static storage. Any thread. */
POSECAL_API const char* posecal_version(void) POSECAL_NOEXCEPT;
/* Message of the last failure on the calling thread ("" after a success). Valid until the next
 * posecal call on this thread. */
POSECAL_API const char* posecal_last_error(void) POSECAL_NOEXCEPT;
/* Name of a status code, e.g. "POSECAL_E_TIMEOUT" ("POSECAL_E_UNKNOWN" for other values).
 * Static storage. Any thread. */
POSECAL_API const char* posecal_status_name(posecal_status status) POSECAL_NOEXCEPT;

/* ---- Context: camera backends, shared by sessions ------------------------------------------ */
typedef struct posecal_context posecal_context;

/* options_json: NULL for defaults, or an object with optional keys
 *   "backends": ["sim", "images", "external", "aravis", "v4l2"]   (which to enable; default all)
 * A URI of a backend that is not enabled is POSECAL_E_UNSUPPORTED. Does not touch hardware. */
POSECAL_API posecal_status posecal_context_create(const char* options_json,
                                                  posecal_context** out) POSECAL_NOEXCEPT;
/* NULL-tolerant. Sessions still open on the context stay usable until they are closed. */
POSECAL_API void posecal_context_destroy(posecal_context* ctx) POSECAL_NOEXCEPT;

/* JSON array of every camera of every enabled backend: objects with "uri", "backend", "id",
 * "vendor", "model", "serial", "transport". A backend that fails to scan is left out. Blocks up
 * to ~1 s while backends scan (GigE Vision discovery). */
POSECAL_API posecal_status posecal_list_cameras(posecal_context* ctx, char* buf,
                                                size_t* size) POSECAL_NOEXCEPT;

/* JSON array of the camera's settings (GenICam features, V4L2 controls, sim:// parameters):
 * objects with "name", "type" ("integer", "float", "boolean", "enumeration", "string",
 * "command", ...), "value" (typed where it parses; null if not readable), "access"
 * ("read-write", "read-only", "write-only", "none"), "unit" (null if none), "range"
 * ({"min", "max"} or null), "options" (enumeration entries or null). Opens the camera for the
 * duration of the call (up to ~3 s for a network camera) without streaming. */
POSECAL_API posecal_status posecal_camera_features(posecal_context* ctx, const char* camera_uri,
                                                   char* buf, size_t* size) POSECAL_NOEXCEPT;

/* Grabs `count` frames (1..100000) and saves them as out_dir/frame_00000.png, ... (8-bit grey
 * or BGR as the camera delivers them for calibration; out_dir is created if missing). Returns
 * JSON {"camera", "out_dir", "files": [{"file", "frame_id", "timestamp_ns", "width", "height",
 * "channels", "source_format"}], "frames_dropped", "frames_incomplete", "wall_ms"}.
 * timeout_ms (1..600000) bounds the whole grab after the camera is open: POSECAL_E_TIMEOUT if
 * the frames did not all arrive in time, POSECAL_E_NOT_FOUND if a finite source (images://)
 * ended, POSECAL_E_DEVICE on a disconnect; the files saved until then stay, and the message says
 * how many. */
POSECAL_API posecal_status posecal_camera_grab(posecal_context* ctx, const char* camera_uri,
                                               int count, const char* out_dir, int timeout_ms,
                                               char* buf, size_t* size) POSECAL_NOEXCEPT;

/* Test-set error of an existing calibration file (any format posecal writes, docs/formats.md):
 * every test frame's board pose is refitted by PnP with the file's intrinsics and eps_test is the
 * RMS reprojection error over all test points (the paper's estimation error).
 *  - sim:// cameras: the fixed 50-frame test set of that simulated camera (the same frames its
 *    sessions' results use), plus "eps_gt" against its ground truth. Computation only, ~1-2 s.
 *  - other cameras: the first "frames" frames that show at least "min_corners" corners of the
 *    board; waits at most "timeout_ms" for them (POSECAL_E_TIMEOUT if none came; fewer frames
 *    are used if the time runs out or a finite source ends).
 * options_json: NULL or an object with optional keys "target" (spec, default the ChArUco board),
 * "frames" (1..1000, 20), "min_corners" (4.., 6), "timeout_ms" (1..600000, 30000).
 * Returns JSON {"result_file", "camera", "target", "source" ("sim_test_set" | "camera"),
 * "frames_seen", "frames_collected", "eps_test", "test_frames", "test_frames_failed",
 * "test_points", "eps_gt" (null unless sim://), "ground_truth" (sim:// only), "model",
 * "image_width", "image_height", "wall_ms"}. POSECAL_E_INVALID_ARGUMENT if the file's image size
 * is not the camera's. */
POSECAL_API posecal_status posecal_evaluate(posecal_context* ctx, const char* result_path,
                                            const char* camera_uri, const char* options_json,
                                            char* buf, size_t* size) POSECAL_NOEXCEPT;

/* ---- Printable targets -------------------------------------------------------------------- */
/* Writes the target (spec like "charuco:9x6:0.028:0.0182:DICT_4X4_50"; NULL = default) at exact
 * physical scale: vector PDF or PNG at `dpi`, chosen by the extension of `path`. Any thread. */
POSECAL_API posecal_status posecal_write_target(const char* target_spec, const char* path,
                                                double dpi, double margin_m) POSECAL_NOEXCEPT;
/* The same with options (docs/board.md): options_json NULL or an object with optional keys
 * "paper" ("board" (default): one page of the board's size; "a4", "a3", "letter": sheets of that
 * size, the board tiled over several when it does not fit one), "dpi" (PNG resolution, 50..2400,
 * default 300), "margin_m" (default 0.01: the white border around the board, on paper the sheet's
 * unprinted edge, at least 5 mm). Each PDF page carries the specification, a 100 mm ruler and
 * "print at 100 %". POSECAL_E_INVALID_ARGUMENT for an unknown key or value, a paper size with a
 * .png, or a board that needs more than 200 sheets; nothing is written then. Any thread. */
POSECAL_API posecal_status posecal_write_target_ex(const char* target_spec, const char* path,
                                                   const char* options_json) POSECAL_NOEXCEPT;

/* Calibration records (session key "records"; docs/c-api.md, "Records"). `location` is the
 * store: a SQLite file or a postgresql:// URL written by sessions with "records". Any thread;
 * each call opens the store itself (waiting up to 10 s for another writer's lock; a server that
 * does not answer is given up after its connect timeout, 10 s). POSECAL_E_IO names the store and
 * the cause if it cannot be opened or is not a posecal record database; POSECAL_E_NOT_FOUND
 * for a run id it does not hold (a unique prefix of a run id is accepted, an ambiguous one is
 * POSECAL_E_INVALID_ARGUMENT).
 * posecal_records_list: a JSON array of the runs, newest first, each {"run_id", "station_id",
 * "operator_id", "lens_id", "camera" {uri, id, vendor, model, serial, transport},
 * "posecal_version", "abi_version", "started", "finished" (null while running or after a
 * kill), "state" (running, converged, failed, interrupted, closed; killed: its process ended
 * without finishing it, found when a later run on the same host began), "verdict" (null,
 * "pass", "fail"), "expected_error_px" (null or a number), "keyframes", "note" (null, or for a
 * killed run which process ended)}. */
POSECAL_API posecal_status posecal_records_list(const char* location, char* buf,
                                                size_t* size) POSECAL_NOEXCEPT;
/* One run: the list's fields and "config" (the session config), "image_width",
 * "image_height", "locked_settings", "result" (the result JSON of posecal_session_result, null
 * if the run ended without a calibration) and "keyframes" [{"index", "time", "corners",
 * "state_before", "state_after", "image_png_bytes"}]. */
POSECAL_API posecal_status posecal_records_show(const char* location, const char* run_id,
                                                char* buf, size_t* size) POSECAL_NOEXCEPT;
/* Re-solves a run from its stored detections, as a journal's resume does (the recorded config,
 * each keyframe in order with the same warm starts): {"run_id", "keyframes", "recorded_by" and
 * "resolved_by" (posecal versions), "identical" (true when the recomputed intrinsics equal, bit
 * for bit, both the last keyframe's estimate and the stored result), "identical_to_last_keyframe",
 * "identical_to_result", "recomputed" {name: value}, "stored" {name: value} or null}. Takes
 * about as long as the run's last recalibrations (well under a second for 10 keyframes); a
 * buffer too small recomputes on the retry. POSECAL_E_STATE for a run of fewer than two
 * keyframes. */
POSECAL_API posecal_status posecal_records_resolve(const char* location, const char* run_id,
                                                   char* buf, size_t* size) POSECAL_NOEXCEPT;
/* Writes the run's re-solved calibration as a model file (format: a name of
 * posecal_session_save_as, or NULL/"" by the extension), atomically. */
POSECAL_API posecal_status posecal_records_export(const char* location, const char* run_id,
                                                  const char* path,
                                                  const char* format) POSECAL_NOEXCEPT;

/* The calibration report (docs/c-api.md, "Reports"): self-contained HTML at html_path (every
 * figure a PNG in a data: URI, <img id="plot-coverage|plot-residuals|plot-distortion|
 * plot-expected-error|plot-sigma|plot-fleet">, a table of the run: id, camera, station,
 * operator, times, versions, verdict and reasons, expected_error_px, keyframes) and, if pdf_path
 * is not NULL or "", a PDF of a title page and one page per figure. Either a run (location and
 * run_id, result_path NULL): its calibration re-solved from the stored keyframes, the coverage,
 * the residuals, the distortion, the expected-error map, sigma of each intrinsic after each
 * keyframe (the prefixes re-solved) and the verdict with the fleet position (the other units of
 * the same camera model and lens id in the store, one per serial); or a result file
 * (result_path, location and run_id NULL): the distortion and, if the file holds the
 * covariance, the expected-error map. Both files are rendered first and then written
 * atomically; an output that cannot be written is POSECAL_E_IO before any work. Returns
 * {"html", "pdf" (or null), "plots" (the figure ids), "pages" (or null), "notes" (what is not
 * shown and why)}; size NULL: no JSON. The files are written even when the buffer is too
 * small (a retry renders them again: pass 64 KiB). Takes well under a second for ten keyframes.
 * POSECAL_E_STATE for a run of fewer than two keyframes; POSECAL_E_INVALID_ARGUMENT for both
 * or neither of a run and a result file, or a result file that is not a camera model. */
POSECAL_API posecal_status posecal_records_report(const char* location, const char* run_id,
                                                  const char* result_path, const char* html_path,
                                                  const char* pdf_path, char* buf,
                                                  size_t* size) POSECAL_NOEXCEPT;

/* Records a session's journal (session key "journal") as a run: the spool for a session whose
 * record store was away (its "records_note" said why), or one recorded before records existed.
 * The camera, config and start time come from the journal, the keyframes (without images) and
 * the locked settings too; the result is the calibration recomputed from the keyframes (as a
 * resume recomputes it; no eps figures, no verdict); the state is the journal's end state, or
 * "interrupted" if it has none. options_json: NULL or {"run_id" (default a new UUID),
 * "station_id", "operator_id", "lens_id"}. Returns {"run_id", "keyframes", "state",
 * "journal_note" (what was dropped from a damaged journal, or null)}. POSECAL_E_STATE for a
 * journal without a frame; a run id already in the store is POSECAL_E_INVALID_ARGUMENT. */
POSECAL_API posecal_status posecal_records_import(const char* location, const char* journal_path,
                                                  const char* options_json, char* buf,
                                                  size_t* size) POSECAL_NOEXCEPT;

/* Callback of session events (posecal_session_set_callback) and of offline progress
 * (posecal_calibrate_images_ex): a kind and a JSON payload, valid only during the call. */
typedef void (*posecal_event_fn)(void* user_data, const char* kind, const char* payload_json);

/* ---- Offline calibration from a folder of images ------------------------------------------ */
typedef struct posecal_calibration posecal_calibration;

/* Calibrates from the images of `images_dir` (name order). The images are first grouped by
 * size (from their headers) and by camera, the file name without its frame number ("left" for
 * left01.jpg .. left14.jpg; a name no other image shares names no camera and goes with the one
 * camera of its size); a folder of several groups needs "camera_group", else
 * POSECAL_E_INVALID_ARGUMENT with a message listing the groups (docs/c-api.md, "Offline").
 * options_json: NULL or an object with optional keys "fix_principal_point", "fix_aspect_ratio",
 * "zero_tangential" (bool), "fixed" (array of parameter names), "min_corners" (int >= 4),
 * "camera_group" (a group's name "left@640x480", its camera "left" or its size "640x480", where
 * that names one group), "spec" (a quality specification file: the result gets a verdict, as a
 * session's). Unreadable images, the other groups' images and images without the
 * target are listed in the result with the reason, not fatal. Blocks for the whole calibration
 * (detection ~50 ms per image plus a solve of well under a second for 20 images). */
POSECAL_API posecal_status posecal_calibrate_images(posecal_context* ctx, const char* images_dir,
                                                    const char* target_spec,
                                                    const char* options_json,
                                                    posecal_calibration** out) POSECAL_NOEXCEPT;
/* The same, calling `progress` (if not NULL) on the calling thread after each image of the
 * group with kind "image" and {"index" (1-based), "total", "file", "corners", "used", and
 * "reason" when not used}. The callback must not throw (a C++ exception is caught and dropped)
 * and must not call into the library. */
POSECAL_API posecal_status posecal_calibrate_images_ex(posecal_context* ctx,
                                                       const char* images_dir,
                                                       const char* target_spec,
                                                       const char* options_json,
                                                       posecal_event_fn progress, void* user_data,
                                                       posecal_calibration** out) POSECAL_NOEXCEPT;
/* Result JSON: "fx" ... "k3", "std" (object, sigma scaled by the residual variance),
 * "std_unit" (sigma at 1 px noise, paper eq. 5), "rms", "frames_used", "frames_rejected",
 * "used", "rejected" ([{"file", "reason"}] in name order), "camera_group" (the group
 * calibrated), "groups" ([{"name", "camera", "width", "height", "images"}]), "per_frame_rms",
 * "covariance" (intrinsics block, scaled), ... */
POSECAL_API posecal_status posecal_calibration_json(const posecal_calibration* cal, char* buf,
                                                    size_t* size) POSECAL_NOEXCEPT;
/* Writes OpenCV YAML (.yml/.yaml), JSON (.json) or XML (.xml) in cv::FileStorage format, or an
 * mrcal model (.cameramodel), by extension; posecal_calibration_save_as names the format. */
POSECAL_API posecal_status posecal_calibration_save(const posecal_calibration* cal,
                                                    const char* path) POSECAL_NOEXCEPT;
/* Writes the calibration in `format`: "opencv" (YAML, or JSON/XML by a .json/.xml path), "ros"
 * (camera_info YAML), "mrcal" (.cameramodel), "kalibr" (camchain YAML, cam0 pinhole-radtan),
 * "halcon" (area_scan_polynomial camera parameters, a fit); NULL or "": by the path's extension,
 * as posecal_calibration_save. docs/formats.md has each format's fields. POSECAL_E_INVALID_ARGUMENT,
 * nothing written, for an unknown format, a path whose extension is another format's, or a model
 * the format cannot hold (Kalibr's radtan has no k3; HALCON's polynomial fits it worse than
 * 0.1 px); the message names the format and the lens model. The file is written atomically. */
POSECAL_API posecal_status posecal_calibration_save_as(const posecal_calibration* cal,
                                                       const char* path,
                                                       const char* format) POSECAL_NOEXCEPT;
POSECAL_API void posecal_calibration_destroy(posecal_calibration* cal) POSECAL_NOEXCEPT;

/* ---- Calibration sessions: one camera, one pose-selection engine --------------------------- */
/* States (docs/c-api.md draws them): opened -> running (engine states "waiting_for_board",
 * "bootstrapping", "initial_pose_1", "initial_pose_2", "refining") -> finished ("converged" or
 * "failed"). Calls not allowed in a state return POSECAL_E_STATE and change nothing. */
typedef struct posecal_session posecal_session;

typedef enum posecal_pixel_format {
  POSECAL_PIXEL_MONO8 = 0,
  POSECAL_PIXEL_BGR8 = 1,
  POSECAL_PIXEL_RGB8 = 2
} posecal_pixel_format;

/* A host image. struct_size = sizeof(posecal_image), set by the caller, so the struct can grow
 * in later ABI versions. width, height in 1..65535; stride_bytes >= width x bytes per pixel.
 * A frame fed to a session must be at least 16x16 (smaller: POSECAL_E_INVALID_ARGUMENT).
 * The library never keeps `data` beyond the call. The layout is frozen (static_asserts in
 * plugin/src/abi_layout.cpp). */
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
 *   "method": "posecal" (default: posecal's engine) | "paper" (the paper's exact method: one
 *   rule pose per target, the variance ratio test) | "reference-std" (the paper's with the
 *   reference implementation's std test); a preset that the other keys override,
 *   "target": spec string (default "charuco:9x6:0.028:0.0182:DICT_4X4_50"),
 *   "operator": "person" | "robot"   (robot: the host reports poses reached),
 *   "convergence_threshold" (0.1), "max_keyframes" (20), "jaccard_threshold" (0.8),
 *   "still_motion_px" (1.5), "track_board" (true: while the board is moved to a target it is
 *   searched around where it was in the last frame, the whole frame when that finds fewer
 *   corners, every 15 frames and for every keyframe; false: the whole frame every time),
 *   "constraint_factor" (5), "target_timeout_frames" (0 = never),
 *   "pose_candidates" (6), "lock_settings" (true), "max_tilt_deg" (70),
 *   "lens_model" ("opencv5"; "opencv8", "opencv12", "opencv14": OpenCV's rational,
 *   thin-prism and tilted-sensor models, coefficients k1 k2 p1 p2 k3 k4 k5 k6 s1 s2 s3 s4
 *   tau_x tau_y in OpenCV's order, so a result drops into cv::undistort; "fisheye": the
 *   Kannala-Brandt model with cv::fisheye's k1..k4; "auto": every one of them fitted after
 *   each keyframe and the one with the lowest Bayesian information criterion calibrated, the
 *   result's "lens_model_choice" naming it with every candidate's figures),
 *   "fixed" ([]: names among the lens model's parameters (fx fy cx cy k1 k2 p1 p2 k3 ...) held at
 * their initial value, 0 for distortion, e.g. ["k2", "k3"] for a narrow lens; they count as
 * converged), "convergence_measure" ("std", the reference implementation's ratio test, the default;
 *   "variance": the paper's, more keyframes), "measured_convergence" (true; false:
 *   parameters converge only when the best next pose would not help, more keyframes, more
 *   accurate; docs/benchmarks.md), "candidate_score" ("projection" | "variance"),
 *   "view_candidates" (300: also score this many random views of the whole board and capture
 *   the best-scored pose, view or rule; 0: rule poses only; docs/pose-selection.md, "Generic
 *   view candidates"),
 *   "view_must_serve_target" (false; true: a view must also reduce the targeted parameter's
 *   variance at least as much as the rule's pose),
 *   "board_timeout_s" (120; 0 = never: the session ends as failed, "failure" in the status
 *   saying so, when no board has been seen for this many seconds of wall time since the first
 *   frame, the last frame showing the board or the camera's return after a disconnect; a
 *   camera that delivers no frame at all fails the same way, counted from the first step),
 *   "accuracy_px" (unset; a number in [0.001, 100]: the session converges when the 90th
 *   percentile of the projection error it predicts, "expected_error_p90_px" of the status and
 *   result, is at most this (9 of 10 such calibrations stay within it), and ends
 *   as not converged at max_keyframes with a reason naming the error reached and the parameter
 *   that holds it back; null unsets it; with method "paper" or "reference-std", which stop on
 *   the ratio test, POSECAL_E_INVALID_ARGUMENT),
 *   "ratio_stop_max_p90_px" (5; a number in [0, 1e6], 0 = off; method "paper" and
 *   "reference-std" set 0): without "accuracy_px", the ratio test's "every parameter converged"
 *   is refused while "expected_error_p90_px" is above this; the parameter that holds the error
 *   back is opened again (event "parameter_reopened") and targeted, and a session that so
 *   reaches max_keyframes ends as not converged with a reason naming the figure,
 *   "journal" (unset; a file path: every keyframe is appended to this journal and flushed to
 *   disk when it is captured, so a kill loses at most the frame in flight; if the file exists
 *   and was recorded with the same camera and config, the session resumes: its keyframes are
 *   restored at the first frame, the calibration recomputed, and status/result say
 *   "resumed_keyframes": N; another camera's or config's journal is POSECAL_E_INVALID_ARGUMENT
 *   naming what differs; a journal cut by a kill resumes from its last complete record and
 *   "journal_note" says so), "journal_images" (false; true: the journal also keeps each
 *   keyframe's image as PNG), "resume" (true; false: an existing journal is renamed to
 *   JOURNAL.<UTC time>.old and a new one started). docs/c-api.md, "Journal";
 *   "spec" (unset; a JSON file of quality limits, read at open: the result gets "verdict"
 *   "pass"/"fail" and "verdict_reasons"; a malformed file is POSECAL_E_INVALID_ARGUMENT naming
 *   the file and the key; docs/c-api.md, "Quality gate");
 *   "records" (unset; a SQLite file, created if needed, or a postgresql:// URL: the run is
 *   recorded there, its
 *   identity at open, every keyframe (detections and image) in its own transaction as it is
 *   captured, the result and verdict when the session finishes or is closed; status and result
 *   say "records", "run_id" and "records_note"; a store that cannot be opened or written does
 *   not stop the calibration: the parts it could not take are written when it is back, at the
 *   next keyframe or the finish, and "records_note" says what is behind), "records_spool"
 *   (unset; a directory: a run the store was still away for at its finish is kept there and
 *   written into the store when a later run opens it), "fleet_outlier_probability" (0.001; with
 *   "records", the finished result's "fleet": its position among the passed units of the same
 *   camera model and lens id in the store, flagged "outlier" beyond the bound that a normal unit
 *   exceeds with this probability; docs/c-api.md, "Fleet outliers"), "prior" ("none"; "fleet"
 *   with "records": the session starts from the mean of those passed units and uses their
 *   spread as a Bayesian prior in the calibration, stopping at "accuracy_px", by default the
 *   fleet's median expected error; the result's "prior" says whether it was used and why not;
 *   docs/c-api.md, "The fleet prior"), "run_id" (unset: a
 *   new random UUID; a run id already in the store is not recorded again), "station_id",
 *   "operator_id", "lens_id" (unset; recorded with the run). docs/c-api.md, "Records".
 * An unknown key is POSECAL_E_INVALID_ARGUMENT. Opening a camera may block up to ~3 s. The
 * camera starts streaming at the first posecal_session_step. */
POSECAL_API posecal_status posecal_session_open(posecal_context* ctx, const char* camera_uri,
                                                const char* config_json,
                                                posecal_session** out) POSECAL_NOEXCEPT;
/* Stops the camera and frees the session. NULL-tolerant. Called from the session's own event
 * callback it does nothing (posecal_last_error says so). */
POSECAL_API void posecal_session_close(posecal_session* session) POSECAL_NOEXCEPT;

/* Takes one frame from the session's camera (waiting at most timeout_ms, 0..600000) and
 * advances the state machine; the frame's processing (board detection, and after a capture a
 * recalibration) adds typically 10-100 ms, up to ~1 s for a recalibration with many keyframes.
 * POSECAL_OK: a frame was processed. POSECAL_E_TIMEOUT: no frame in time.
 * POSECAL_E_DEVICE: the camera is disconnected (keyframes are kept; keep stepping to resume when
 * it is back). POSECAL_E_STATE: the calibration has finished, an "external" session (use
 * posecal_session_feed), or called from the event callback. POSECAL_E_NOT_FOUND: a finite
 * source (images://) has no more frames. */
POSECAL_API posecal_status posecal_session_step(posecal_session* session,
                                                int timeout_ms) POSECAL_NOEXCEPT;
/* Processes a host frame synchronously (the state machine has advanced when it returns; same
 * cost as a step without the wait). For any session; "external" sessions get frames only this
 * way. All frames of a session must have the same size. POSECAL_E_STATE once finished. */
POSECAL_API posecal_status posecal_session_feed(posecal_session* session,
                                                const posecal_image* image) POSECAL_NOEXCEPT;

/* Current status JSON: "state", "finished", "converged", "keyframes", "target_parameter",
 * "guidance", "has_target", "jaccard", "still", "motion_px", "board_visible", "corners",
 * "corners_required", "pose_reached", "captured", "image_width", "image_height", "frames",
 * "camera_connected", "camera", "parameters": {"fx": {"value", "std", "converged"}, ...}.
 * Allowed in the event callback. */
POSECAL_API posecal_status posecal_session_status(posecal_session* session, char* buf,
                                                  size_t* size) POSECAL_NOEXCEPT;
/* The board pose to reach: rotation vector and translation (metres) of the board frame in the
 * camera frame. POSECAL_E_STATE when there is no target (before the first frame or the board,
 * or finished). Allowed in the event callback. */
POSECAL_API posecal_status posecal_session_target_pose(posecal_session* session, double rvec[3],
                                                       double tvec[3]) POSECAL_NOEXCEPT;
/* Robot mode: the robot has reached the current target; the session captures as soon as the
 * board is seen and still (the Jaccard check does not gate a robot's capture).
 * POSECAL_E_STATE for a person session, without a target, or once finished. */
POSECAL_API posecal_status posecal_session_pose_reached(posecal_session* session) POSECAL_NOEXCEPT;
/* Gives up on the current refinement target (e.g. a robot cannot reach it) and generates the
 * next one. POSECAL_E_STATE outside the refinement. */
POSECAL_API posecal_status posecal_session_skip_target(posecal_session* session) POSECAL_NOEXCEPT;
/* Copies the last processed frame into a host image of the camera's size, converted to the
 * image's format. POSECAL_E_STATE before the first frame. */
POSECAL_API posecal_status posecal_session_last_frame(posecal_session* session,
                                                      posecal_image* out) POSECAL_NOEXCEPT;
/* Draws the guidance overlay (target board, detected corners, text) into a host image of the
 * camera's size, in place. POSECAL_E_STATE before the first frame. */
POSECAL_API posecal_status posecal_session_render_overlay(posecal_session* session,
                                                          posecal_image* inout) POSECAL_NOEXCEPT;
/* The map behind "expected_error_px": fills a host float image of width x height (each in
 * [2, 16384]; rows row_stride_bytes apart, 0 = width * 4) with the predicted RMS projection
 * error in pixels, at the measured corner noise, at points spread from image edge to image edge:
 * value (i, j) is for pixel (i (W - 1) / (width - 1), j (H - 1) / (height - 1)) of the W x H
 * camera image, so width = W and height = H give one value per pixel. NaN where the estimated
 * lens has no ray. Its RMS over a 40 x 23 map is "expected_error_px". POSECAL_E_STATE before the
 * second keyframe and inside the event callback. */
POSECAL_API posecal_status posecal_session_expected_error_map(posecal_session* session, float* out,
                                                              int width, int height,
                                                              size_t row_stride_bytes) POSECAL_NOEXCEPT;
/* Result JSON: "converged", "state", model values "fx" ... "k3", "std", "std_unit",
 * "covariance", "eps_res", "expected_error_px" (the predicted RMS projection error over the
 * image at the measured corner noise; "expected_error_unit_px" at 1 px noise;
 * "expected_error_mean_px" and "expected_error_p90_px": the mean and 90th percentile of the
 * mean distance over the image that such a calibration realises;
 * "expected_error_limited_by": the intrinsic whose uncertainty contributes most), "keyframes", "frames_processed", "camera" identity, "target",
 * "locked_settings", "parameter_converged", "started"/"finished" timestamps; for sim:// cameras
 * also "eps_test", "eps_gt", "test_frames" and "ground_truth" (the first call after a new
 * keyframe renders the test set: ~1 s). POSECAL_E_STATE before the second keyframe (no
 * calibration yet). Allowed in the event callback. */
POSECAL_API posecal_status posecal_session_result(posecal_session* session, char* buf,
                                                  size_t* size) POSECAL_NOEXCEPT;
/* Saves the calibration by extension: OpenCV YAML (.yml/.yaml), JSON (.json) or XML (.xml), or
 * mrcal (.cameramodel). The OpenCV file holds the model, the standard deviations, the intrinsics
 * covariance (scaled, as the result's "covariance"), expected_error_px, and "converged" and
 * "interrupted" as the integers 0/1. POSECAL_E_STATE before the second keyframe. */
POSECAL_API posecal_status posecal_session_save(posecal_session* session,
                                                const char* path) POSECAL_NOEXCEPT;
/* posecal_session_save in a named `format` (NULL or "": by extension), with the formats and
 * errors of posecal_calibration_save_as. */
POSECAL_API posecal_status posecal_session_save_as(posecal_session* session, const char* path,
                                                   const char* format) POSECAL_NOEXCEPT;

/* Stops the calibration gracefully, e.g. when the host is asked to quit: no further frame is
 * processed (posecal_session_step and _feed return POSECAL_E_STATE), status and result say
 * "interrupted": true and "finished": true, and what was calibrated so far can still be read
 * (posecal_session_result) and saved (posecal_session_save writes "interrupted: 1" and
 * "converged: 0" into the OpenCV file). A calibration that has already finished keeps its outcome.
 * Idempotent. Thread: any thread, also while another is inside posecal_session_step (that call
 * finishes its frame first); also allowed in the event callback. Not async-signal-safe: from a
 * signal handler set a flag and call this from a thread. */
POSECAL_API posecal_status posecal_session_interrupt(posecal_session* session) POSECAL_NOEXCEPT;

/* Events: called with a kind ("state_changed", "captured", "keyframe_rejected", "calibrated",
 * "parameter_converged", "parameter_reopened", "target_changed", "target_skipped",
 * "camera_disconnected", "camera_reconnected", "error") and a JSON payload ({"keyframes", "frames",
 * "message", and "from"/"to" for state_changed, "parameter" where one is concerned}). Thread:
 * always the thread that is inside posecal_session_step or posecal_session_feed, before that call
 * returns; never a library thread. Inside the callback only posecal_session_status,
 * posecal_session_target_pose, posecal_session_result and posecal_last_error may be called on
 * the same session (every other session call returns POSECAL_E_STATE); other sessions and
 * contexts may be used as usual. The strings are valid only during the call. The callback must
 * not throw (a C++ exception is caught and dropped) and should return quickly: the frame waits.
 * fn = NULL removes the callback. Not allowed inside the callback. */
POSECAL_API posecal_status posecal_session_set_callback(posecal_session* session,
                                                        posecal_event_fn fn,
                                                        void* user_data) POSECAL_NOEXCEPT;

#ifdef __cplusplus
}
#endif

#endif /* POSECAL_H */
