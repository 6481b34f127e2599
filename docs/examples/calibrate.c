/*
 * calibrate.c - a complete host of the posecal C ABI (docs/c-api.md).
 *
 * Opens a calibration session on a camera, prints every event, steps the camera until the
 * calibration has converged (or failed, or the time is up), prints the result and saves it.
 *
 *   cc -std=c99 calibrate.c $(pkg-config --cflags --libs posecal) -o calibrate
 *   ./calibrate "sim://?seed=1" camera.yml
 *
 * Exit code: 0 converged, 3 finished without converging, 2 failure.
 */
#include <posecal.h>
#include <stdio.h>
#include <stdlib.h>
#include <string.h>

/* Prints a failed call's status and message, and returns 2 (the failure exit code). */
static int fail(const char* what, posecal_status status) {
  fprintf(stderr, "%s: %s (%s)\n", what, posecal_last_error(), posecal_status_name(status));
  return 2;
}

/* Calls a JSON-returning function twice: once to learn the size, once to fill the buffer.
 * Returns a malloc'ed string or NULL (the status is in *status). */
static char* session_json(posecal_status (*fn)(posecal_session*, char*, size_t*),
                          posecal_session* session, posecal_status* status) {
  size_t size = 0;
  *status = fn(session, NULL, &size);
  if (*status != POSECAL_E_BUFFER_TOO_SMALL) return NULL;
  char* buf = malloc(size);
  if (buf == NULL) return NULL;
  *status = fn(session, buf, &size);
  if (*status != POSECAL_OK) {
    free(buf);
    return NULL;
  }
  return buf;
}

/* Events arrive on the thread that is inside posecal_session_step, before it returns. */
static void on_event(void* user_data, const char* kind, const char* payload_json) {
  int* captured = (int*)user_data;
  if (strcmp(kind, "captured") == 0) ++*captured;
  printf("event %-20s %s\n", kind, payload_json);
}

int main(int argc, char** argv) {
  const char* uri = argc > 1 ? argv[1] : "sim://?seed=1";
  const char* out = argc > 2 ? argv[2] : "camera.yml";

  if (posecal_abi_version() != POSECAL_ABI_VERSION) {
    fprintf(stderr, "libposecal has ABI %u, this program was built for %u\n", posecal_abi_version(),
            POSECAL_ABI_VERSION);
    return 2;
  }

  posecal_context* ctx = NULL;
  posecal_status s = posecal_context_create(NULL, &ctx);
  if (s != POSECAL_OK) return fail("posecal_context_create", s);

  posecal_session* session = NULL;
  s = posecal_session_open(ctx, uri, "{\"max_keyframes\": 25}", &session);
  if (s != POSECAL_OK) {
    posecal_context_destroy(ctx);
    return fail("posecal_session_open", s);
  }

  int captured = 0;
  posecal_session_set_callback(session, on_event, &captured);

  int exit_code = 0;
  for (int frame = 0; frame < 5000; ++frame) {
    s = posecal_session_step(session, 2000 /* ms */);
    if (s == POSECAL_OK) continue;
    if (s == POSECAL_E_STATE) break; /* the calibration has finished */
    if (s == POSECAL_E_TIMEOUT || s == POSECAL_E_DEVICE) {
      /* No frame in time, or the camera is unplugged: keyframes are kept, keep stepping. */
      fprintf(stderr, "waiting: %s\n", posecal_last_error());
      continue;
    }
    exit_code = fail("posecal_session_step", s);
    break;
  }

  char* result = session_json(posecal_session_result, session, &s);
  if (result == NULL) {
    if (exit_code == 0) exit_code = fail("posecal_session_result", s);
  } else {
    printf("result %s\n", result);
    s = posecal_session_save(session, out);
    if (s != POSECAL_OK) {
      exit_code = fail("posecal_session_save", s);
    } else {
      printf("%d keyframes captured, calibration written to %s\n", captured, out);
      if (exit_code == 0 && strstr(result, "\"converged\":true") == NULL) exit_code = 3;
    }
    free(result);
  }

  posecal_session_close(session);
  posecal_context_destroy(ctx);
  return exit_code;
}
