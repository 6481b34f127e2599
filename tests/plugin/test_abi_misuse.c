/*
 * ABI misuse: every entry point of posecal.h called with every kind of bad argument (NULL
 * handles and pointers, too small buffers, malformed JSON, unknown keys, wrong types, unknown
 * URIs, calls in the wrong state, re-entrant calls from the event callback, bad images). Each
 * call must return the documented status with a non-empty posecal_last_error(), change nothing,
 * and never crash. Compiled as C; built twice by tests/plugin/CMakeLists.txt: against
 * libposecal.so and against the AddressSanitizer + UBSan copy libposecal_asan.so.
 *
 * usage: test_abi_misuse WORK_DIR
 */
#include <pthread.h>
#include <stdio.h>
#include <stdlib.h>
#include <string.h>
#include <time.h>
#include <unistd.h>

#include "posecal.h"

static int g_failures = 0;
static int g_checks = 0;

#define CHECK(cond)                                                            \
  do {                                                                         \
    ++g_checks;                                                                \
    if (!(cond)) {                                                             \
      ++g_failures;                                                            \
      fprintf(stderr, "%s:%d: CHECK failed: %s\n", __FILE__, __LINE__, #cond); \
    }                                                                          \
  } while (0)

/* The call must fail with `expected` and leave a message. */
#define EXPECT_STATUS(call, expected)                                                           \
  do {                                                                                          \
    const posecal_status s_ = (call);                                                           \
    const char* m_ = posecal_last_error();                                                      \
    ++g_checks;                                                                                 \
    if (s_ != (expected)) {                                                                     \
      ++g_failures;                                                                             \
      fprintf(stderr, "%s:%d: %s returned %s, expected %s (%s)\n", __FILE__, __LINE__, #call,   \
              posecal_status_name(s_), posecal_status_name(expected), m_);                      \
    } else if ((expected) != POSECAL_OK && (m_ == NULL || m_[0] == '\0')) {                     \
      ++g_failures;                                                                             \
      fprintf(stderr, "%s:%d: %s: no error message\n", __FILE__, __LINE__, #call);              \
    } else if ((expected) == POSECAL_OK && m_[0] != '\0') {                                     \
      ++g_failures;                                                                             \
      fprintf(stderr, "%s:%d: %s succeeded but left message '%s'\n", __FILE__, __LINE__, #call, \
              m_);                                                                              \
    }                                                                                           \
  } while (0)

#define EXPECT_OK(call) EXPECT_STATUS(call, POSECAL_OK)
#define EXPECT_INVALID(call) EXPECT_STATUS(call, POSECAL_E_INVALID_ARGUMENT)
#define EXPECT_STATE(call) EXPECT_STATUS(call, POSECAL_E_STATE)

/* The message of the last failure mentions `word`. */
static void expect_message(const char* word, int line) {
  ++g_checks;
  if (strstr(posecal_last_error(), word) == NULL) {
    ++g_failures;
    fprintf(stderr, "%s:%d: message '%s' does not mention '%s'\n", __FILE__, line,
            posecal_last_error(), word);
  }
}
#define EXPECT_MESSAGE(word) expect_message(word, __LINE__)

static char g_dir[360];

/* Prints how long each part took (the sanitizer build runs ~3x slower). */
static void lap(const char* what) {
  static struct timespec last;
  struct timespec now;
  clock_gettime(CLOCK_MONOTONIC, &now);
  if (last.tv_sec != 0) {
    printf("%-22s %6.2f s\n", what,
           (double)(now.tv_sec - last.tv_sec) + 1e-9 * (double)(now.tv_nsec - last.tv_nsec));
  }
  last = now;
}

static const char* path_in(const char* name) {
  static char buf[4][1200];
  static int i = 0;
  i = (i + 1) % 4;
  snprintf(buf[i], sizeof buf[i], "%s/%s", g_dir, name);
  return buf[i];
}

static int count_files(const char* dir) {
  char cmd[1400];
  snprintf(cmd, sizeof cmd, "ls -1 '%s' 2>/dev/null | wc -l", dir);
  FILE* p = popen(cmd, "r");
  int n = -1;
  if (p) {
    if (fscanf(p, "%d", &n) != 1) n = -1;
    pclose(p);
  }
  return n;
}

/* ---- global functions ---------------------------------------------------------------------- */
static void test_globals(void) {
  CHECK(posecal_abi_version() == POSECAL_ABI_VERSION);
  CHECK(posecal_version() != NULL && posecal_version()[0] != '\0');
  CHECK(strcmp(posecal_status_name(POSECAL_E_TIMEOUT), "POSECAL_E_TIMEOUT") == 0);
  CHECK(strcmp(posecal_status_name((posecal_status)999), "POSECAL_E_UNKNOWN") == 0);
  for (int s = 0; s <= 10; ++s)
    CHECK(strncmp(posecal_status_name((posecal_status)s), "POSECAL_", 8) == 0);
  CHECK(posecal_last_error() != NULL);
}

/* Errors are per thread: a failure here is not seen by another thread. */
static void* other_thread_error(void* arg) {
  (void)arg;
  return (void*)(size_t)strlen(posecal_last_error());
}

static void test_per_thread_error(void) {
  posecal_context* ctx = NULL;
  EXPECT_INVALID(posecal_context_create("{\"bogus\": 1}", &ctx));
  pthread_t t;
  void* len = NULL;
  CHECK(pthread_create(&t, NULL, other_thread_error, NULL) == 0);
  CHECK(pthread_join(t, &len) == 0);
  CHECK((size_t)len == 0);
  CHECK(strstr(posecal_last_error(), "bogus") != NULL); /* still ours */
}

/* ---- context -------------------------------------------------------------------------------- */
static void test_context(void) {
  posecal_context* ctx = (posecal_context*)0x1;
  EXPECT_INVALID(posecal_context_create(NULL, NULL));
  EXPECT_INVALID(posecal_context_create("{", &ctx));
  CHECK(ctx == NULL); /* out is cleared on failure */
  EXPECT_INVALID(posecal_context_create("[]", &ctx));
  EXPECT_INVALID(posecal_context_create("42", &ctx));
  EXPECT_INVALID(posecal_context_create("{\"bogus\": 1}", &ctx));
  EXPECT_MESSAGE("bogus");
  EXPECT_INVALID(posecal_context_create("{\"backends\": \"sim\"}", &ctx));
  EXPECT_INVALID(posecal_context_create("{\"backends\": [1]}", &ctx));
  EXPECT_INVALID(posecal_context_create("{\"backends\": [\"nope\"]}", &ctx));
  EXPECT_MESSAGE("nope");
  CHECK(ctx == NULL);
  posecal_context_destroy(NULL);

  /* A backend that is not enabled. */
  EXPECT_OK(posecal_context_create("{\"backends\": [\"sim\", \"external\"]}", &ctx));
  posecal_session* s = NULL;
  EXPECT_STATUS(posecal_session_open(ctx, "images:///tmp", NULL, &s), POSECAL_E_UNSUPPORTED);
  CHECK(s == NULL);
  EXPECT_OK(posecal_session_open(ctx, "sim://?seed=3", "", &s));
  posecal_session_close(s);
  /* A context destroyed before its sessions: they stay usable until closed. */
  posecal_session* a = NULL;
  posecal_session* b = NULL;
  EXPECT_OK(posecal_session_open(ctx, "sim://?seed=4", NULL, &a));
  EXPECT_OK(posecal_session_open(ctx, "external", NULL, &b));
  posecal_context_destroy(ctx);
  EXPECT_OK(posecal_session_step(a, 1000));
  {
    static unsigned char px[32 * 32];
    const posecal_image img = {sizeof(posecal_image), 32, 32, 32, POSECAL_PIXEL_MONO8, px};
    EXPECT_OK(posecal_session_feed(b, &img));
  }
  posecal_session_close(a);
  posecal_session_close(b);
}

/* ---- list, features, grab, evaluate, targets ------------------------------------------------ */
static void test_camera_calls(posecal_context* ctx) {
  char buf[8] = "XXXXXXX";
  size_t size = 0;

  EXPECT_INVALID(posecal_list_cameras(NULL, buf, &size));
  EXPECT_INVALID(posecal_list_cameras(ctx, buf, NULL));
  size = 0;
  EXPECT_STATUS(posecal_list_cameras(ctx, NULL, &size), POSECAL_E_BUFFER_TOO_SMALL);
  CHECK(size > sizeof buf);
  size = sizeof buf;
  EXPECT_STATUS(posecal_list_cameras(ctx, buf, &size), POSECAL_E_BUFFER_TOO_SMALL);
  CHECK(strcmp(buf, "XXXXXXX") == 0); /* untouched */
  {
    char* big = malloc(size);
    size_t n = size;
    EXPECT_OK(posecal_list_cameras(ctx, big, &n));
    CHECK(n == size && strlen(big) + 1 == n && big[0] == '[');
    free(big);
  }

  /* features */
  EXPECT_INVALID(posecal_camera_features(NULL, "sim://", buf, &size));
  EXPECT_INVALID(posecal_camera_features(ctx, NULL, buf, &size));
  EXPECT_INVALID(posecal_camera_features(ctx, "sim://", buf, NULL));
  EXPECT_INVALID(posecal_camera_features(ctx, "nosuch://x", NULL, &size));
  EXPECT_MESSAGE("nosuch");
  EXPECT_INVALID(posecal_camera_features(ctx, "", NULL, &size));
  EXPECT_INVALID(posecal_camera_features(ctx, "sim://?bogus=1", NULL, &size));
  EXPECT_STATUS(posecal_camera_features(ctx, "images:///nonexistent/dir", NULL, &size),
                POSECAL_E_NOT_FOUND);
  size = 0;
  EXPECT_STATUS(posecal_camera_features(ctx, "sim://?seed=2", NULL, &size),
                POSECAL_E_BUFFER_TOO_SMALL);
  {
    char* big = malloc(size);
    size_t n = size;
    EXPECT_OK(posecal_camera_features(ctx, "sim://?seed=2", big, &n));
    CHECK(strstr(big, "\"name\":\"Width\"") != NULL);
    free(big);
  }

  /* grab */
  const char* grab_dir = path_in("grab");
  EXPECT_INVALID(posecal_camera_grab(NULL, "sim://", 1, grab_dir, 1000, buf, &size));
  EXPECT_INVALID(posecal_camera_grab(ctx, NULL, 1, grab_dir, 1000, buf, &size));
  EXPECT_INVALID(posecal_camera_grab(ctx, "sim://", 1, NULL, 1000, buf, &size));
  EXPECT_INVALID(posecal_camera_grab(ctx, "sim://", 1, grab_dir, 1000, buf, NULL));
  EXPECT_INVALID(posecal_camera_grab(ctx, "sim://", 0, grab_dir, 1000, buf, &size));
  EXPECT_INVALID(posecal_camera_grab(ctx, "sim://", -3, grab_dir, 1000, buf, &size));
  EXPECT_INVALID(posecal_camera_grab(ctx, "sim://", 1, grab_dir, 0, buf, &size));
  EXPECT_INVALID(posecal_camera_grab(ctx, "sim://", 1, grab_dir, 600001, buf, &size));
  EXPECT_INVALID(posecal_camera_grab(ctx, "nosuch://", 1, grab_dir, 1000, buf, &size));
  EXPECT_STATUS(posecal_camera_grab(ctx, "sim://", 1, "/proc/posecal_no/dir", 1000, buf, &size),
                POSECAL_E_IO);
  EXPECT_STATUS(posecal_camera_grab(ctx, "external", 1, grab_dir, 50, buf, &size),
                POSECAL_E_TIMEOUT);
  /* Too small a buffer: the frames are grabbed once; the retry returns the kept JSON. */
  size = 4;
  EXPECT_STATUS(posecal_camera_grab(ctx, "sim://?seed=5", 2, grab_dir, 20000, buf, &size),
                POSECAL_E_BUFFER_TOO_SMALL);
  CHECK(count_files(grab_dir) == 2);
  {
    char* big = malloc(size);
    size_t n = size;
    EXPECT_OK(posecal_camera_grab(ctx, "sim://?seed=5", 2, grab_dir, 20000, big, &n));
    CHECK(strstr(big, "frame_00001.png") != NULL);
    free(big);
  }
  CHECK(count_files(grab_dir) == 2);
  /* A finite source that ends before `count` frames. */
  {
    char uri[1200];
    snprintf(uri, sizeof uri, "images://%s", grab_dir);
    EXPECT_STATUS(posecal_camera_grab(ctx, uri, 5, path_in("regrab"), 20000, NULL, &size),
                  POSECAL_E_NOT_FOUND);
    EXPECT_MESSAGE("2 of 5");
  }

  /* targets */
  EXPECT_INVALID(posecal_write_target(NULL, NULL, 300, 0.01));
  EXPECT_INVALID(posecal_write_target("charuco:9x6", path_in("t.png"), 300, 0.01));
  EXPECT_INVALID(posecal_write_target("nonsense", path_in("t.png"), 300, 0.01));
  CHECK(posecal_write_target(NULL, "/proc/posecal_no/board.png", 300, 0.01) != POSECAL_OK);
  CHECK(posecal_last_error()[0] != '\0');
  EXPECT_OK(posecal_write_target(NULL, path_in("board/board.png"), 50, 0.01));
  EXPECT_INVALID(posecal_write_target_ex(NULL, NULL, NULL));
  EXPECT_INVALID(posecal_write_target_ex(NULL, path_in("t.pdf"), "{\"paper\": \"a5\"}"));
  EXPECT_MESSAGE("a5");
  EXPECT_INVALID(posecal_write_target_ex(NULL, path_in("t.pdf"), "{\"papers\": \"a4\"}"));
  EXPECT_INVALID(posecal_write_target_ex(NULL, path_in("t.pdf"), "{\"dpi\": 1e9}"));
  EXPECT_INVALID(posecal_write_target_ex(NULL, path_in("t.pdf"), "[1]"));
  EXPECT_INVALID(posecal_write_target_ex(NULL, path_in("t.png"), "{\"paper\": \"a4\"}"));
  EXPECT_INVALID(posecal_write_target_ex("chessboard:99x99:0.5", path_in("t.pdf"),
                                         "{\"paper\": \"a4\"}"));
  EXPECT_MESSAGE("sheets");
  EXPECT_OK(posecal_write_target_ex(NULL, path_in("board/board_a4.pdf"),
                                    "{\"paper\": \"a4\", \"margin_m\": 0.008}"));
  EXPECT_OK(posecal_write_target_ex(NULL, path_in("board/board_ex.png"), NULL));
}

static void test_evaluate(posecal_context* ctx, const char* result_path) {
  char result_file[400]; /* path_in() reuses its buffers */
  snprintf(result_file, sizeof result_file, "%s", result_path);
  char buf[16];
  size_t size = sizeof buf;
  EXPECT_INVALID(posecal_evaluate(NULL, result_file, "sim://", NULL, buf, &size));
  EXPECT_INVALID(posecal_evaluate(ctx, NULL, "sim://", NULL, buf, &size));
  EXPECT_INVALID(posecal_evaluate(ctx, result_file, NULL, NULL, buf, &size));
  EXPECT_INVALID(posecal_evaluate(ctx, result_file, "sim://", NULL, buf, NULL));
  EXPECT_INVALID(posecal_evaluate(ctx, result_file, "sim://", "{", buf, &size));
  EXPECT_INVALID(posecal_evaluate(ctx, result_file, "sim://", "{\"bogus\":1}", buf, &size));
  EXPECT_MESSAGE("bogus");
  EXPECT_INVALID(posecal_evaluate(ctx, result_file, "sim://", "{\"frames\":0}", buf, &size));
  EXPECT_INVALID(posecal_evaluate(ctx, result_file, "sim://", "{\"frames\":\"x\"}", buf, &size));
  EXPECT_INVALID(posecal_evaluate(ctx, result_file, "sim://", "{\"timeout_ms\":-1}", buf, &size));
  EXPECT_INVALID(
      posecal_evaluate(ctx, result_file, "sim://", "{\"target\":\"charuco\"}", buf, &size));
  EXPECT_INVALID(posecal_evaluate(ctx, result_file, "nosuch://", NULL, buf, &size));
  CHECK(posecal_evaluate(ctx, path_in("missing.yml"), "sim://", NULL, buf, &size) != POSECAL_OK);
  CHECK(posecal_last_error()[0] != '\0');
  EXPECT_STATUS(posecal_evaluate(ctx, result_file, "external", NULL, buf, &size),
                POSECAL_E_UNSUPPORTED);
  /* A board image of another size than the calibration's camera. */
  {
    char uri[1200];
    snprintf(uri, sizeof uri, "images://%s", path_in("board"));
    EXPECT_INVALID(posecal_evaluate(ctx, result_file, uri, NULL, buf, &size));
    EXPECT_MESSAGE("1280x720");
    /* No board at all in a finite source. */
    snprintf(uri, sizeof uri, "images://%s", path_in("grab"));
    EXPECT_STATUS(
        posecal_evaluate(ctx, result_file, uri, "{\"target\":\"chessboard:7x5:0.03\"}", buf, &size),
        POSECAL_E_DEGENERATE);
  }
  /* The buffer protocol, on the two grabbed frames (sim:// evaluation is tested elsewhere: it
   * renders a 50-frame test set, slow under the sanitizers). */
  {
    char uri[400];
    snprintf(uri, sizeof uri, "images://%s", path_in("grab"));
    size = sizeof buf;
    EXPECT_STATUS(posecal_evaluate(ctx, result_file, uri, NULL, buf, &size),
                  POSECAL_E_BUFFER_TOO_SMALL);
    char* big = malloc(size);
    size_t n = size;
    EXPECT_OK(posecal_evaluate(ctx, result_file, uri, NULL, big, &n));
    CHECK(strstr(big, "\"eps_test\":") != NULL && strstr(big, "\"eps_gt\":null") != NULL);
    CHECK(strstr(big, "\"frames_collected\":2") != NULL);
    free(big);
  }
}

/* ---- offline calibration -------------------------------------------------------------------- */
static void test_offline(posecal_context* ctx) {
  posecal_calibration* cal = (posecal_calibration*)0x1;
  EXPECT_INVALID(posecal_calibrate_images(NULL, g_dir, NULL, NULL, &cal));
  EXPECT_INVALID(posecal_calibrate_images(ctx, NULL, NULL, NULL, &cal));
  EXPECT_INVALID(posecal_calibrate_images(ctx, g_dir, NULL, NULL, NULL));
  EXPECT_STATUS(posecal_calibrate_images(ctx, "/nonexistent/posecal", NULL, NULL, &cal),
                POSECAL_E_NOT_FOUND);
  CHECK(cal == NULL);
  EXPECT_INVALID(posecal_calibrate_images(ctx, g_dir, "charuco:9", NULL, &cal));
  EXPECT_INVALID(posecal_calibrate_images(ctx, g_dir, NULL, "{", &cal));
  EXPECT_INVALID(posecal_calibrate_images(ctx, g_dir, NULL, "{\"bogus\":true}", &cal));
  EXPECT_INVALID(posecal_calibrate_images(ctx, g_dir, NULL, "{\"min_corners\":\"x\"}", &cal));
  EXPECT_INVALID(posecal_calibrate_images(ctx, g_dir, NULL, "{\"min_corners\":2}", &cal));
  EXPECT_INVALID(posecal_calibrate_images(ctx, g_dir, NULL, "{\"fixed\":\"k3\"}", &cal));
  EXPECT_INVALID(posecal_calibrate_images(ctx, g_dir, NULL, "{\"fixed\":[\"k9\"]}", &cal));
  EXPECT_INVALID(posecal_calibrate_images(ctx, g_dir, NULL, "{\"zero_tangential\":1}", &cal));
  /* A folder without images. */
  CHECK(posecal_calibrate_images(ctx, path_in("empty"), NULL, NULL, &cal) != POSECAL_OK);
  CHECK(posecal_last_error()[0] != '\0');
  CHECK(cal == NULL);
  size_t size = 0;
  EXPECT_INVALID(posecal_calibration_json(NULL, NULL, &size));
  EXPECT_INVALID(posecal_calibration_save(NULL, path_in("x.yml")));
  EXPECT_INVALID(posecal_calibration_save_as(NULL, path_in("x.yml"), "ros"));
  posecal_calibration_destroy(NULL);
}

/* ---- sessions ------------------------------------------------------------------------------- */
struct Reentry {
  posecal_session* s;
  int calls;
  posecal_status step, feed, close_status, set_cb, pose_reached, skip, save, render, last_frame;
  posecal_status error_map;
  posecal_status status, target, result;
  int close_message_ok;
};

static void reentrant_callback(void* user, const char* kind, const char* payload) {
  struct Reentry* r = (struct Reentry*)user;
  (void)payload;
  if (strcmp(kind, "captured") != 0 || r->calls++ > 0) return;
  unsigned char px[16 * 16];
  posecal_image img = {sizeof(posecal_image), 16, 16, 16, POSECAL_PIXEL_MONO8, px};
  memset(px, 0, sizeof px);
  r->step = posecal_session_step(r->s, 0);
  r->feed = posecal_session_feed(r->s, &img);
  posecal_session_close(r->s); /* must not close: we are inside its callback */
  r->close_message_ok = strstr(posecal_last_error(), "callback") != NULL;
  r->set_cb = posecal_session_set_callback(r->s, NULL, NULL);
  r->pose_reached = posecal_session_pose_reached(r->s);
  r->skip = posecal_session_skip_target(r->s);
  r->save = posecal_session_save(r->s, path_in("cb.yml"));
  r->render = posecal_session_render_overlay(r->s, &img);
  r->last_frame = posecal_session_last_frame(r->s, &img);
  float map[4 * 4];
  r->error_map = posecal_session_expected_error_map(r->s, map, 4, 4, 0);
  char buf[65536];
  size_t size = sizeof buf;
  r->status = posecal_session_status(r->s, buf, &size);
  double rv[3], tv[3];
  r->target = posecal_session_target_pose(r->s, rv, tv);
  size = sizeof buf;
  r->result = posecal_session_result(r->s, buf, &size);
}

static void test_session_arguments(posecal_context* ctx) {
  posecal_session* s = (posecal_session*)0x1;
  EXPECT_INVALID(posecal_session_open(NULL, "sim://", NULL, &s));
  CHECK(s == NULL);
  EXPECT_INVALID(posecal_session_open(ctx, NULL, NULL, &s));
  EXPECT_INVALID(posecal_session_open(ctx, "sim://", NULL, NULL));
  EXPECT_INVALID(posecal_session_open(ctx, "sim://", "{", &s));
  EXPECT_INVALID(posecal_session_open(ctx, "sim://", "[1]", &s));
  EXPECT_INVALID(posecal_session_open(ctx, "sim://", "{\"bogus\":1}", &s));
  EXPECT_MESSAGE("bogus");
  EXPECT_INVALID(posecal_session_open(ctx, "sim://", "{\"max_keyframes\":\"many\"}", &s));
  EXPECT_INVALID(posecal_session_open(ctx, "sim://", "{\"max_keyframes\":1}", &s));
  /* accuracy_px: a positive finite number (null unsets it). */
  EXPECT_INVALID(posecal_session_open(ctx, "sim://", "{\"accuracy_px\":0}", &s));
  EXPECT_MESSAGE("accuracy_px");
  EXPECT_INVALID(posecal_session_open(ctx, "sim://", "{\"accuracy_px\":-1}", &s));
  EXPECT_INVALID(posecal_session_open(ctx, "sim://", "{\"accuracy_px\":1e400}", &s));
  EXPECT_INVALID(posecal_session_open(ctx, "sim://", "{\"accuracy_px\":\"0.2\"}", &s));
  EXPECT_MESSAGE("accuracy_px");
  EXPECT_INVALID(posecal_session_open(ctx, "sim://", "{\"max_keyframes\":null}", &s));
  EXPECT_MESSAGE("max_keyframes");
  EXPECT_OK(posecal_session_open(ctx, "sim://", "{\"accuracy_px\":null}", &s));
  posecal_session_close(s);
  s = (posecal_session*)0x1;
  EXPECT_INVALID(posecal_session_open(ctx, "sim://", "{\"max_keyframes\":2.5}", &s));
  EXPECT_INVALID(posecal_session_open(ctx, "sim://", "{\"convergence_threshold\":2}", &s));
  EXPECT_INVALID(posecal_session_open(ctx, "sim://", "{\"lock_settings\":\"yes\"}", &s));
  EXPECT_INVALID(posecal_session_open(ctx, "sim://", "{\"operator\":\"cat\"}", &s));
  EXPECT_INVALID(posecal_session_open(ctx, "sim://", "{\"fixed\":\"k3\"}", &s));
  EXPECT_INVALID(posecal_session_open(ctx, "sim://", "{\"fixed\":[3]}", &s));
  EXPECT_INVALID(posecal_session_open(ctx, "sim://", "{\"fixed\":[\"k9\"]}", &s));
  EXPECT_MESSAGE("k9");
  EXPECT_INVALID(posecal_session_open(ctx, "sim://", "{\"convergence_measure\":\"cat\"}", &s));
  EXPECT_MESSAGE("convergence_measure");
  EXPECT_INVALID(posecal_session_open(ctx, "sim://", "{\"measured_convergence\":\"no\"}", &s));
  EXPECT_INVALID(posecal_session_open(ctx, "sim://", "{\"view_candidates\":-1}", &s));
  EXPECT_MESSAGE("view_candidates");
  EXPECT_INVALID(posecal_session_open(ctx, "sim://", "{\"view_candidates\":5000}", &s));
  EXPECT_INVALID(posecal_session_open(ctx, "sim://", "{\"view_candidates\":2.5}", &s));
  EXPECT_INVALID(posecal_session_open(ctx, "sim://", "{\"view_must_serve_target\":\"yes\"}", &s));
  EXPECT_INVALID(posecal_session_open(ctx, "sim://", "{\"target\":\"charuco:1x1\"}", &s));
  EXPECT_INVALID(
      posecal_session_open(ctx, "sim://?operator=robot", "{\"operator\":\"person\"}", &s));
  EXPECT_INVALID(posecal_session_open(ctx, "nosuch://camera", NULL, &s));
  EXPECT_INVALID(posecal_session_open(ctx, "not a uri:/", NULL, &s));
  EXPECT_INVALID(posecal_session_open(ctx, "sim://?bogus=1", NULL, &s));
  EXPECT_INVALID(posecal_session_open(ctx, "sim://?seed=-4", NULL, &s));
  EXPECT_STATUS(posecal_session_open(ctx, "images:///nonexistent/posecal", NULL, &s),
                POSECAL_E_NOT_FOUND);
  CHECK(posecal_session_open(ctx, "sim://?model=/nonexistent.yml", NULL, &s) != POSECAL_OK);
  CHECK(posecal_last_error()[0] != '\0');
  CHECK(s == NULL);

  /* NULL session everywhere. */
  char buf[64];
  size_t size = sizeof buf;
  double rv[3], tv[3];
  unsigned char px[64];
  posecal_image img = {sizeof(posecal_image), 8, 8, 8, POSECAL_PIXEL_MONO8, px};
  EXPECT_INVALID(posecal_session_step(NULL, 10));
  EXPECT_INVALID(posecal_session_feed(NULL, &img));
  EXPECT_INVALID(posecal_session_status(NULL, buf, &size));
  EXPECT_INVALID(posecal_session_target_pose(NULL, rv, tv));
  EXPECT_INVALID(posecal_session_pose_reached(NULL));
  EXPECT_INVALID(posecal_session_skip_target(NULL));
  EXPECT_INVALID(posecal_session_interrupt(NULL));
  EXPECT_INVALID(posecal_session_last_frame(NULL, &img));
  EXPECT_INVALID(posecal_session_render_overlay(NULL, &img));
  float map[4 * 4];
  EXPECT_INVALID(posecal_session_expected_error_map(NULL, map, 4, 4, 0));
  EXPECT_INVALID(posecal_session_result(NULL, buf, &size));
  EXPECT_INVALID(posecal_session_save(NULL, path_in("x.yml")));
  EXPECT_INVALID(posecal_session_set_callback(NULL, NULL, NULL));
  posecal_session_close(NULL);
}

/* Bad host images on an external session; then the frame-size rule. */
static void test_images(posecal_context* ctx) {
  posecal_session* s = NULL;
  EXPECT_OK(posecal_session_open(ctx, "external", NULL, &s));
  if (!s) return;
  enum { W = 64, H = 48 };
  static unsigned char px[W * H * 3];
  memset(px, 90, sizeof px);
  const posecal_image good = {sizeof(posecal_image), W, H, W, POSECAL_PIXEL_MONO8, px};
  posecal_image img;

  EXPECT_INVALID(posecal_session_feed(s, NULL));
  img = good;
  img.struct_size = sizeof(posecal_image) - 1;
  EXPECT_INVALID(posecal_session_feed(s, &img));
  EXPECT_MESSAGE("struct_size");
  img = good;
  img.struct_size = 0;
  EXPECT_INVALID(posecal_session_feed(s, &img));
  img = good;
  img.width = 0;
  EXPECT_INVALID(posecal_session_feed(s, &img));
  img = good;
  img.height = -5;
  EXPECT_INVALID(posecal_session_feed(s, &img));
  img = good;
  img.width = 70000;
  EXPECT_INVALID(posecal_session_feed(s, &img));
  img = good;
  img.format = 7;
  EXPECT_INVALID(posecal_session_feed(s, &img));
  EXPECT_MESSAGE("format");
  img = good;
  img.format = -1;
  EXPECT_INVALID(posecal_session_feed(s, &img));
  img = good;
  img.stride_bytes = W - 1;
  EXPECT_INVALID(posecal_session_feed(s, &img));
  EXPECT_MESSAGE("stride");
  img = good;
  img.format = POSECAL_PIXEL_BGR8; /* stride W < 3 W */
  EXPECT_INVALID(posecal_session_feed(s, &img));
  img = good;
  img.data = NULL;
  EXPECT_INVALID(posecal_session_feed(s, &img));
  EXPECT_STATE(posecal_session_step(s, 10)); /* external: no camera to step */
  img = good;
  EXPECT_STATE(posecal_session_last_frame(s, &img));

  /* Good frames in every format, and a padded stride. */
  img = good;
  EXPECT_OK(posecal_session_feed(s, &img));
  img = good;
  img.format = POSECAL_PIXEL_BGR8;
  img.stride_bytes = 3 * W;
  EXPECT_OK(posecal_session_feed(s, &img));
  img = good;
  img.format = POSECAL_PIXEL_RGB8;
  img.stride_bytes = 3 * W;
  EXPECT_OK(posecal_session_feed(s, &img));
  img = good;
  img.stride_bytes = 2 * W;
  img.height = H / 2;
  EXPECT_INVALID(posecal_session_feed(s, &img)); /* another size than the first frame */
  EXPECT_MESSAGE("size");

  /* last_frame / render_overlay: size and format of the host image. */
  static unsigned char out[W * H * 3];
  img = (posecal_image){sizeof(posecal_image), W, H, 3 * W, POSECAL_PIXEL_RGB8, out};
  EXPECT_OK(posecal_session_last_frame(s, &img));
  CHECK(out[0] == 90 && out[3 * W * H - 1] == 90);
  EXPECT_OK(posecal_session_render_overlay(s, &img));
  img.width = W - 1;
  EXPECT_INVALID(posecal_session_last_frame(s, &img));
  EXPECT_INVALID(posecal_session_render_overlay(s, &img));
  img.width = W;
  img.struct_size = 4;
  EXPECT_INVALID(posecal_session_render_overlay(s, &img));

  /* No board: no target, no result. */
  double rv[3], tv[3];
  char buf[64];
  size_t size = sizeof buf;
  EXPECT_STATE(posecal_session_target_pose(s, rv, tv));
  EXPECT_STATE(posecal_session_result(s, buf, &size));
  EXPECT_STATE(posecal_session_save(s, path_in("none.yml")));
  EXPECT_STATE(posecal_session_skip_target(s));
  EXPECT_STATE(posecal_session_pose_reached(s));
  posecal_session_close(s);
}

/* posecal_session_interrupt: no frame after it, status says so, idempotent. */
static void test_interrupt(posecal_context* ctx) {
  posecal_session* s = NULL;
  char buf[8192];
  size_t size = sizeof buf;
  EXPECT_OK(posecal_session_open(ctx, "sim://?seed=2", NULL, &s));
  if (!s) return;
  for (int i = 0; i < 3; ++i) EXPECT_OK(posecal_session_step(s, 5000));
  EXPECT_OK(posecal_session_interrupt(s));
  EXPECT_OK(posecal_session_interrupt(s));
  EXPECT_STATE(posecal_session_step(s, 100));
  EXPECT_MESSAGE("interrupted");
  EXPECT_OK(posecal_session_status(s, buf, &size));
  CHECK(strstr(buf, "\"interrupted\":true") != NULL);
  CHECK(strstr(buf, "\"finished\":true") != NULL);
  EXPECT_STATE(posecal_session_result(s, buf, &size)); /* no keyframes yet */
  posecal_session_close(s);
}

static void test_session_states(posecal_context* ctx) {
  posecal_session* s = NULL;
  char small[8];
  size_t size;
  double rv[3], tv[3];
  static unsigned char px[1280 * 720 * 3];
  posecal_image img = {sizeof(posecal_image), 1280, 720, 1280 * 3, POSECAL_PIXEL_BGR8, px};

  /* Person session on the simulated camera. */
  EXPECT_OK(posecal_session_open(ctx, "sim://?seed=1", NULL, &s));
  if (!s) return;
  /* Before the first frame. */
  EXPECT_STATE(posecal_session_target_pose(s, rv, tv));
  EXPECT_STATE(posecal_session_pose_reached(s));
  EXPECT_MESSAGE("robot");
  EXPECT_STATE(posecal_session_skip_target(s));
  EXPECT_STATE(posecal_session_last_frame(s, &img));
  EXPECT_STATE(posecal_session_render_overlay(s, &img));
  {
    float map[4 * 4];
    EXPECT_STATE(posecal_session_expected_error_map(s, map, 4, 4, 0));
    EXPECT_MESSAGE("two keyframes");
  }
  size = sizeof small;
  EXPECT_STATE(posecal_session_result(s, small, &size));
  EXPECT_STATE(posecal_session_save(s, path_in("early.yml")));
  EXPECT_INVALID(posecal_session_step(s, -1));
  EXPECT_INVALID(posecal_session_step(s, 600001));
  EXPECT_INVALID(posecal_session_status(s, small, NULL));
  size = 0;
  EXPECT_STATUS(posecal_session_status(s, NULL, &size), POSECAL_E_BUFFER_TOO_SMALL);
  CHECK(size > 10);
  size = sizeof small;
  memset(small, 'Z', sizeof small);
  EXPECT_STATUS(posecal_session_status(s, small, &size), POSECAL_E_BUFFER_TOO_SMALL);
  CHECK(small[0] == 'Z' && small[7] == 'Z');

  /* Two frames: the board is seen, no keyframes yet: result before two keyframes. */
  EXPECT_OK(posecal_session_step(s, 1000));
  EXPECT_OK(posecal_session_step(s, 1000));
  size = sizeof small;
  EXPECT_STATE(posecal_session_result(s, small, &size));
  EXPECT_MESSAGE("two keyframes");
  EXPECT_STATE(posecal_session_save(s, path_in("early.yml")));
  EXPECT_STATE(posecal_session_pose_reached(s)); /* person session */
  EXPECT_INVALID(posecal_session_target_pose(s, NULL, tv));
  EXPECT_INVALID(posecal_session_target_pose(s, rv, NULL));
  EXPECT_OK(posecal_session_last_frame(s, &img));
  EXPECT_OK(posecal_session_render_overlay(s, &img));

  /* Re-entrant calls from the event callback. */
  struct Reentry r;
  memset(&r, 0, sizeof r);
  r.s = s;
  EXPECT_OK(posecal_session_set_callback(s, reentrant_callback, &r));
  for (int i = 0; i < 400 && r.calls == 0; ++i) {
    if (posecal_session_step(s, 1000) != POSECAL_OK) break;
  }
  CHECK(r.calls > 0);
  CHECK(r.step == POSECAL_E_STATE);
  CHECK(r.feed == POSECAL_E_STATE);
  CHECK(r.close_message_ok);
  CHECK(r.set_cb == POSECAL_E_STATE);
  CHECK(r.pose_reached == POSECAL_E_STATE);
  CHECK(r.skip == POSECAL_E_STATE);
  CHECK(r.save == POSECAL_E_STATE);
  CHECK(r.render == POSECAL_E_STATE);
  CHECK(r.last_frame == POSECAL_E_STATE);
  CHECK(r.error_map == POSECAL_E_STATE);
  CHECK(r.status == POSECAL_OK);
  CHECK(r.target == POSECAL_OK || r.target == POSECAL_E_STATE);
  CHECK(r.result == POSECAL_OK || r.result == POSECAL_E_STATE);
  EXPECT_OK(posecal_session_set_callback(s, NULL, NULL));
  /* The session survived the attempt to close it from inside. */
  size = 0;
  EXPECT_STATUS(posecal_session_status(s, NULL, &size), POSECAL_E_BUFFER_TOO_SMALL);

  /* Frames of a wrong size for this camera. */
  {
    static unsigned char tiny[32 * 32];
    posecal_image t = {sizeof(posecal_image), 32, 32, 32, POSECAL_PIXEL_MONO8, tiny};
    EXPECT_INVALID(posecal_session_feed(s, &t));
  }
  posecal_session_close(s);

  /* Robot session: pose_reached before the first frame, then run to the end. */
  s = NULL;
  /* Three keyframes at most: the session finishes ("failed", with a result) after a few dozen
   * frames; convergence itself is plugin_c_abi's business. */
  EXPECT_OK(
      posecal_session_open(ctx, "sim://?seed=1&operator=robot", "{\"max_keyframes\": 3}", &s));
  if (!s) return;
  EXPECT_STATE(posecal_session_pose_reached(s));
  int frames = 0, saved_checks = 0;
  posecal_status st = POSECAL_OK;
  for (; frames < 2000; ++frames) {
    st = posecal_session_step(s, 1000);
    if (st != POSECAL_OK) break;
    size = 0;
    if (!saved_checks && posecal_session_result(s, NULL, &size) == POSECAL_E_BUFFER_TOO_SMALL) {
      /* In the middle of the calibration (a result exists): bad extension or path. */
      saved_checks = 1;
      EXPECT_INVALID(posecal_session_save(s, path_in("result.txt")));
      EXPECT_INVALID(posecal_session_save(s, NULL));
      CHECK(posecal_session_save(s, "/proc/posecal_no/result.yml") != POSECAL_OK);
      CHECK(posecal_last_error()[0] != '\0');
      /* The expected-error map: buffer, grid size and stride. */
      float map[6 * 5 + 8];
      EXPECT_INVALID(posecal_session_expected_error_map(s, NULL, 6, 5, 0));
      EXPECT_INVALID(posecal_session_expected_error_map(s, map, 1, 5, 0));
      EXPECT_INVALID(posecal_session_expected_error_map(s, map, 6, 16385, 0));
      EXPECT_INVALID(posecal_session_expected_error_map(s, map, 6, 5, 6 * 4 - 4));
      EXPECT_INVALID(posecal_session_expected_error_map(s, map, 6, 5, 6 * 4 + 2));
      EXPECT_MESSAGE("row_stride_bytes");
      map[6 * 5] = -7.0f;
      EXPECT_OK(posecal_session_expected_error_map(s, map, 6, 5, 0));
      CHECK(map[0] > 0 && map[6 * 5 - 1] > 0 && map[6 * 5] == -7.0f); /* packed: nothing beyond */
      EXPECT_OK(posecal_session_expected_error_map(s, map, 3, 5, 8 * 4)); /* rows 8 floats apart */
      CHECK(map[0] > 0 && map[8 * 4 + 2] > 0);
    }
  }
  CHECK(saved_checks);
  CHECK(st == POSECAL_E_STATE); /* finished */
  EXPECT_STATE(posecal_session_step(s, 10));
  EXPECT_MESSAGE("finished");
  EXPECT_STATE(posecal_session_feed(s, &img));
  EXPECT_STATE(posecal_session_pose_reached(s));
  EXPECT_STATE(posecal_session_skip_target(s));
  EXPECT_STATE(posecal_session_target_pose(s, rv, tv));
  EXPECT_OK(posecal_session_save(s, path_in("result.yml")));
  EXPECT_OK(posecal_session_save(s, path_in("result.json")));
  /* Named formats (docs/formats.md): NULL or "" is by extension; an unknown name or a file name
   * of another format is refused naming it. */
  EXPECT_OK(posecal_session_save_as(s, path_in("result.cameramodel"), NULL));
  EXPECT_OK(posecal_session_save_as(s, path_in("result.xml"), ""));
  EXPECT_OK(posecal_session_save_as(s, path_in("result_ros.yaml"), "ros"));
  EXPECT_INVALID(posecal_session_save_as(s, path_in("result_x.yml"), "halcon9"));
  EXPECT_MESSAGE("halcon9");
  EXPECT_INVALID(posecal_session_save_as(s, path_in("result_ros.json"), "ros"));
  EXPECT_MESSAGE("result_ros.json");
  EXPECT_INVALID(posecal_session_save_as(NULL, path_in("x.yml"), "ros"));
  EXPECT_INVALID(posecal_session_save_as(s, NULL, "ros"));
  /* (the result itself is checked by plugin_c_abi: for sim:// it renders the test set) */
  size = 0;
  EXPECT_STATUS(posecal_session_status(s, NULL, &size), POSECAL_E_BUFFER_TOO_SMALL);
  {
    char* big = malloc(size);
    size_t n = size;
    EXPECT_OK(posecal_session_status(s, big, &n));
    CHECK(strstr(big, "\"state\":\"failed\"") != NULL && strstr(big, "\"keyframes\":3") != NULL);
    free(big);
  }
  posecal_session_close(s);
}

/* Records: a session interrupted after a few frames is recorded as "interrupted"; the readers
 * refuse bad arguments, unreadable stores and unknown runs, each naming the cause. */
static void test_records(posecal_context* ctx) {
  char db[600], config[800], buf[16384], model[700];
  snprintf(db, sizeof db, "%s", path_in("records.sqlite"));
  snprintf(model, sizeof model, "%s", path_in("record.yml"));
  snprintf(config, sizeof config, "{\"records\": \"%s\", \"run_id\": \"misuse-1\"}", db);
  posecal_session* s = NULL;
  EXPECT_OK(posecal_session_open(ctx, "sim://?seed=2", config, &s));
  if (!s) return;
  for (int i = 0; i < 3; ++i) EXPECT_OK(posecal_session_step(s, 5000));
  EXPECT_OK(posecal_session_interrupt(s));
  size_t size = sizeof buf;
  EXPECT_OK(posecal_session_status(s, buf, &size));
  CHECK(strstr(buf, "\"run_id\":\"misuse-1\"") != NULL);
  posecal_session_close(s);

  size = sizeof buf;
  EXPECT_OK(posecal_records_list(db, buf, &size));
  CHECK(strstr(buf, "\"state\":\"interrupted\"") != NULL);
  size = sizeof buf;
  EXPECT_OK(posecal_records_show(db, "misuse", buf, &size)); /* a unique prefix */
  CHECK(strstr(buf, "\"result\":null") != NULL);            /* no calibration yet */
  EXPECT_INVALID(posecal_records_list(NULL, buf, &size));
  EXPECT_INVALID(posecal_records_list(db, buf, NULL));
  EXPECT_INVALID(posecal_records_show(db, NULL, buf, &size));
  EXPECT_INVALID(posecal_records_show(db, "", buf, &size));
  EXPECT_INVALID(posecal_records_resolve(NULL, "misuse-1", buf, &size));
  EXPECT_INVALID(posecal_records_export(db, "misuse-1", NULL, NULL));
  EXPECT_STATUS(posecal_records_show(db, "no-such-run", buf, &size), POSECAL_E_NOT_FOUND);
  EXPECT_MESSAGE("no-such-run");
  EXPECT_STATUS(posecal_records_resolve(db, "misuse-1", buf, &size), POSECAL_E_STATE);
  EXPECT_MESSAGE("keyframes");
  EXPECT_STATUS(posecal_records_export(db, "misuse-1", model, NULL), POSECAL_E_STATE);
  /* The report: an output path, a run or a result file (not both), a run with a calibration;
   * nothing is written when it fails. */
  char html[700];
  snprintf(html, sizeof html, "%s", path_in("report.html"));
  EXPECT_INVALID(posecal_records_report(db, "misuse-1", NULL, NULL, NULL, buf, &size));
  EXPECT_INVALID(posecal_records_report(NULL, NULL, NULL, html, NULL, buf, &size));
  EXPECT_INVALID(posecal_records_report(db, "misuse-1", model, html, NULL, buf, &size));
  EXPECT_MESSAGE("not both");
  EXPECT_STATUS(posecal_records_report(db, "misuse-1", NULL, html, NULL, buf, &size),
                POSECAL_E_STATE);
  EXPECT_MESSAGE("keyframes");
  EXPECT_STATUS(
      posecal_records_report(db, "misuse-1", NULL, path_in("none/r.html"), NULL, buf, &size),
      POSECAL_E_IO);
  EXPECT_MESSAGE("none");
  CHECK(posecal_records_report(NULL, NULL, db, html, NULL, NULL, NULL) != POSECAL_OK);
  EXPECT_MESSAGE("records.sqlite"); /* a record store is not a model file */
  CHECK(access(html, F_OK) != 0);
  EXPECT_STATUS(posecal_records_list(path_in("empty"), buf, &size), POSECAL_E_IO); /* a directory */
  EXPECT_MESSAGE("empty");
  /* A PostgreSQL server that is not there (port 1 refuses): the error names the store. */
  EXPECT_STATUS(posecal_records_list("postgresql://127.0.0.1:1/r", buf, &size), POSECAL_E_IO);
  EXPECT_MESSAGE("postgresql://127.0.0.1:1/r");
  size = sizeof buf;
  EXPECT_INVALID(posecal_records_import(NULL, path_in("x.journal"), NULL, buf, &size));
  EXPECT_INVALID(posecal_records_import(db, NULL, NULL, buf, &size));
  EXPECT_INVALID(posecal_records_import(db, db, "{\"lens\": 1}", buf, &size));
  EXPECT_MESSAGE("lens");
  EXPECT_STATUS(posecal_records_import(db, path_in("no.journal"), NULL, buf, &size), POSECAL_E_IO);
  CHECK(posecal_records_import(db, db, NULL, buf, &size) != POSECAL_OK); /* not a journal */
  CHECK(posecal_last_error()[0] != '\0');
  char small[8];
  size = sizeof small;
  EXPECT_STATUS(posecal_records_list(db, small, &size), POSECAL_E_BUFFER_TOO_SMALL);
  CHECK(size > sizeof small);
}

int main(int argc, char** argv) {
  if (argc != 2) {
    fprintf(stderr, "usage: %s WORK_DIR\n", argv[0]);
    return 2;
  }
  snprintf(g_dir, sizeof g_dir, "%s", argv[1]);
  {
    char cmd[1200];
    snprintf(cmd, sizeof cmd, "rm -rf '%s' && mkdir -p '%s/board' '%s/empty'", g_dir, g_dir, g_dir);
    if (system(cmd) != 0) return 2;
  }
  lap("start");
  test_globals();
  test_per_thread_error();
  test_context();
  lap("globals, context");
  posecal_context* ctx = NULL;
  EXPECT_OK(posecal_context_create(NULL, &ctx));
  if (!ctx) return 1;
  test_camera_calls(ctx);
  lap("camera calls");
  test_offline(ctx);
  lap("offline");
  test_session_arguments(ctx);
  lap("session arguments");
  test_images(ctx);
  lap("images");
  test_session_states(ctx);
  test_interrupt(ctx);
  lap("session states");
  test_evaluate(ctx, path_in("result.yml"));
  lap("evaluate");
  test_records(ctx);
  lap("records");
  posecal_context_destroy(ctx);
  printf("%d checks, %d failures\n", g_checks, g_failures);
  return g_failures == 0 ? 0 : 1;
}
