/*
 * The C ABI as a C host sees it: the library is loaded with dlopen() (no link-time dependency,
 * only the header), the ABI version is checked, a complete sim:// calibration runs through
 * posecal_session_step until it converges, and two sessions calibrate at the same time on two
 * threads sharing one context. Compiled as C.
 *
 * usage: test_c_abi /path/to/libposecal.so WORK_DIR
 */
#include <dlfcn.h>
#include <pthread.h>
#include <stdio.h>
#include <stdlib.h>
#include <string.h>
#include <sys/stat.h>
#include <time.h>

#include "posecal.h"

/* The entry points this host uses, resolved by name. */
static struct {
  unsigned (*abi_version)(void);
  const char* (*version)(void);
  const char* (*last_error)(void);
  const char* (*status_name)(posecal_status);
  posecal_status (*context_create)(const char*, posecal_context**);
  void (*context_destroy)(posecal_context*);
  posecal_status (*session_open)(posecal_context*, const char*, const char*, posecal_session**);
  void (*session_close)(posecal_session*);
  posecal_status (*session_step)(posecal_session*, int);
  posecal_status (*session_status)(posecal_session*, char*, size_t*);
  posecal_status (*session_result)(posecal_session*, char*, size_t*);
  posecal_status (*session_save)(posecal_session*, const char*);
  posecal_status (*session_target_pose)(posecal_session*, double*, double*);
  posecal_status (*session_set_callback)(posecal_session*, posecal_event_fn, void*);
} api;

static int g_failures = 0;
#define CHECK(cond)                                                                            \
  do {                                                                                         \
    if (!(cond)) {                                                                             \
      ++g_failures;                                                                            \
      fprintf(stderr, "%s:%d: CHECK failed: %s (last error: %s)\n", __FILE__, __LINE__, #cond, \
              api.last_error ? api.last_error() : "?");                                        \
    }                                                                                          \
  } while (0)

static int resolve(void* lib, const char* name, void* fn_ptr, size_t fn_size) {
  void* sym = dlsym(lib, name);
  if (sym == NULL) {
    fprintf(stderr, "missing symbol %s\n", name);
    return 0;
  }
  /* ISO C has no object-to-function pointer conversion; POSIX guarantees the representation. */
  memcpy(fn_ptr, &sym, fn_size);
  return 1;
}
#define RESOLVE(field, name) ok &= resolve(lib, name, &api.field, sizeof api.field)

static double now_s(void) {
  struct timespec ts;
  clock_gettime(CLOCK_MONOTONIC, &ts);
  return (double)ts.tv_sec + 1e-9 * (double)ts.tv_nsec;
}

/* JSON through the size protocol; the caller frees. */
static char* fetch(posecal_status (*fn)(posecal_session*, char*, size_t*), posecal_session* s) {
  size_t size = 0;
  if (fn(s, NULL, &size) != POSECAL_E_BUFFER_TOO_SMALL || size == 0) return NULL;
  char* buf = malloc(size);
  size_t n = size;
  if (fn(s, buf, &n) != POSECAL_OK || n != size || strlen(buf) + 1 != size) {
    free(buf);
    return NULL;
  }
  return buf;
}

struct Run {
  posecal_context* ctx;
  const char* uri;
  const char* save_path;
  /* results */
  int converged;
  int frames;
  int events;
  int events_on_other_threads;
  int targets_seen;
  double t_start, t_end, wall_s;
  pthread_t thread;
};

static void on_event(void* user, const char* kind, const char* payload) {
  struct Run* r = (struct Run*)user;
  ++r->events;
  /* Documented: the callback runs on the thread inside posecal_session_step. */
  if (!pthread_equal(pthread_self(), r->thread)) ++r->events_on_other_threads;
  if (strcmp(kind, "target_changed") == 0) ++r->targets_seen;
  if (payload == NULL || payload[0] != '{') ++r->events_on_other_threads; /* malformed */
}

static void* calibrate(void* arg) {
  struct Run* r = (struct Run*)arg;
  r->thread = pthread_self();
  const double t0 = now_s();
  r->t_start = t0;
  posecal_session* s = NULL;
  if (api.session_open(r->ctx, r->uri, "{\"max_keyframes\": 30}", &s) != POSECAL_OK) {
    fprintf(stderr, "open %s: %s\n", r->uri, api.last_error());
    return NULL;
  }
  CHECK(api.session_set_callback(s, on_event, r) == POSECAL_OK);
  posecal_status st = POSECAL_OK;
  for (r->frames = 0; r->frames < 2000; ++r->frames) {
    st = api.session_step(s, 1000);
    if (st != POSECAL_OK) break;
  }
  CHECK(st == POSECAL_E_STATE); /* the documented "finished" */
  char* status = fetch(api.session_status, s);
  CHECK(status != NULL);
  if (status) r->converged = strstr(status, "\"state\":\"converged\"") != NULL;
  free(status);
  if (r->save_path) {
    /* The result (for a sim:// camera it renders the test set once: ~1.5 s, so only here). */
    char* result = fetch(api.session_result, s);
    CHECK(result != NULL);
    if (result) {
      CHECK(strstr(result, "\"converged\":true") != NULL);
      CHECK(strstr(result, "\"eps_test\":") != NULL);
      CHECK(strstr(result, "\"fx\":") != NULL);
    }
    free(result);
  }
  double rv[3], tv[3];
  CHECK(api.session_target_pose(s, rv, tv) == POSECAL_E_STATE); /* no target once finished */
  if (r->save_path) CHECK(api.session_save(s, r->save_path) == POSECAL_OK);
  api.session_close(s);
  r->t_end = now_s();
  r->wall_s = r->t_end - t0;
  return NULL;
}

int main(int argc, char** argv) {
  if (argc != 3) {
    fprintf(stderr, "usage: %s LIBPOSECAL WORK_DIR\n", argv[0]);
    return 2;
  }
  mkdir(argv[2], 0755); /* may exist already */
  void* lib = dlopen(argv[1], RTLD_NOW | RTLD_LOCAL);
  if (lib == NULL) {
    fprintf(stderr, "dlopen: %s\n", dlerror());
    return 1;
  }
  int ok = 1;
  RESOLVE(abi_version, "posecal_abi_version");
  RESOLVE(version, "posecal_version");
  RESOLVE(last_error, "posecal_last_error");
  RESOLVE(status_name, "posecal_status_name");
  RESOLVE(context_create, "posecal_context_create");
  RESOLVE(context_destroy, "posecal_context_destroy");
  RESOLVE(session_open, "posecal_session_open");
  RESOLVE(session_close, "posecal_session_close");
  RESOLVE(session_step, "posecal_session_step");
  RESOLVE(session_status, "posecal_session_status");
  RESOLVE(session_result, "posecal_session_result");
  RESOLVE(session_save, "posecal_session_save");
  RESOLVE(session_target_pose, "posecal_session_target_pose");
  RESOLVE(session_set_callback, "posecal_session_set_callback");
  if (!ok) return 1;
  /* Only the C ABI is exported: an internal C++ symbol must not resolve. */
  CHECK(dlsym(lib,
              "_ZN7posecal3abi9set_errorERKNSt7__cxx1112basic_stringIcSt11char_traitsIcESaIcEEE") ==
        NULL);

  CHECK(api.abi_version() == POSECAL_ABI_VERSION);
  printf("libposecal %s, ABI %u\n", api.version(), api.abi_version());
  CHECK(strcmp(api.status_name(POSECAL_E_STATE), "POSECAL_E_STATE") == 0);

  posecal_context* ctx = NULL;
  CHECK(api.context_create(NULL, &ctx) == POSECAL_OK && ctx != NULL);
  if (!ctx) return 1;

  /* 1. One complete calibration on this thread. */
  char save_path[1200];
  snprintf(save_path, sizeof save_path, "%s/c_abi_seed21.yml", argv[2]);
  struct Run single = {.ctx = ctx, .uri = "sim://?seed=21", .save_path = save_path};
  calibrate(&single);
  printf("single: converged %d after %d frames, %d events, %.2f s\n", single.converged,
         single.frames, single.events, single.wall_s);
  CHECK(single.converged);
  CHECK(single.events > 5 && single.targets_seen >= 2);
  CHECK(single.events_on_other_threads == 0);
  /* 2. Two sessions at the same time on two threads (one context). */
  struct Run runs[2] = {{.ctx = ctx, .uri = "sim://?seed=22"},
                        {.ctx = ctx, .uri = "sim://?seed=23&operator=robot"}};
  pthread_t threads[2];
  const double t0 = now_s();
  for (int i = 0; i < 2; ++i) CHECK(pthread_create(&threads[i], NULL, calibrate, &runs[i]) == 0);
  for (int i = 0; i < 2; ++i) CHECK(pthread_join(threads[i], NULL) == 0);
  const double wall = now_s() - t0;
  for (int i = 0; i < 2; ++i) {
    printf("thread %d (%s): converged %d after %d frames, %d events, %.2f s\n", i, runs[i].uri,
           runs[i].converged, runs[i].frames, runs[i].events, runs[i].wall_s);
    CHECK(runs[i].converged);
    CHECK(runs[i].events_on_other_threads == 0);
  }
  /* The two calibrations were running at the same time. */
  printf("both: %.2f s wall\n", wall);
  CHECK(runs[0].t_start < runs[1].t_end && runs[1].t_start < runs[0].t_end);

  api.context_destroy(ctx);
  dlclose(lib);
  if (g_failures) {
    fprintf(stderr, "%d failures\n", g_failures);
    return 1;
  }
  printf("ok\n");
  return 0;
}
