/* The smallest host of an installed libposecal: version check and a few frames of sim://. */
#include <posecal.h>
#include <stdio.h>
#include <string.h>

int main(void) {
  if (posecal_abi_version() != POSECAL_ABI_VERSION) return 1;
  posecal_context* ctx = NULL;
  posecal_session* s = NULL;
  if (posecal_context_create(NULL, &ctx) != POSECAL_OK) return 1;
  if (posecal_session_open(ctx, "sim://?seed=3", NULL, &s) != POSECAL_OK) return 1;
  for (int i = 0; i < 3; ++i) {
    if (posecal_session_step(s, 1000) != POSECAL_OK) return 1;
  }
  char buf[65536];
  size_t size = sizeof buf;
  if (posecal_session_status(s, buf, &size) != POSECAL_OK) return 1;
  const int ok = strstr(buf, "\"frames\":3") != NULL;
  posecal_session_close(s);
  posecal_context_destroy(ctx);
  printf("consumer: libposecal %s, %s\n", posecal_version(), ok ? "ok" : "unexpected status");
  return ok ? 0 : 1;
}
