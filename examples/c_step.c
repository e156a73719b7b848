/* Calls a C step library (torchcontact export estimator --format c) from C: no Python at all.
 *
 * Export and build (the header is NAME.h beside NAME.so; its symbols use the default prefix):
 *
 *   torchcontact export estimator --robot tcarm --slot forearm_skin:force \
 *       --slot hand_skin:force --format c --out arm.so
 *   cc -O2 -include arm.h examples/c_step.c arm.so -Wl,-rpath,$PWD -lm -o c_step
 *
 * Usage:
 *   c_step               frames on stdin: TC_ESTIMATOR_IN_SIZE numbers each (the packed input
 *                        vector, offsets in the header), one output line per frame: the status
 *                        then the TC_ESTIMATOR_OUT_SIZE numbers of the packed output (%.17g)
 *   c_step --defaults    print the default input vector (offsets and inertial parameters of the
 *                        correction stack, all slots inactive) and exit
 *   c_step --bench N     time N calls on the last frame read from stdin (or the defaults with
 *                        q = 0.1): prints p50 and p99 in ns
 *   c_step --meta        print the library's JSON metadata
 */
#ifndef TC_ESTIMATOR_IN_SIZE
#include "tc_estimator.h"
#endif
#include <stdio.h>
#include <stdlib.h>
#include <string.h>
#include <time.h>

static int cmp_i64(const void* a, const void* b) {
  int64_t x = *(const int64_t*)a, y = *(const int64_t*)b;
  return (x > y) - (x < y);
}

static int64_t now_ns(void) {
  struct timespec ts;
  clock_gettime(CLOCK_MONOTONIC, &ts);
  return (int64_t)ts.tv_sec * 1000000000 + ts.tv_nsec;
}

/* Reads one frame of TC_ESTIMATOR_IN_SIZE numbers; returns 1 on success, 0 at the end. */
static int read_frame(tc_estimator_real* x) {
  for (int i = 0; i < TC_ESTIMATOR_IN_SIZE; ++i) {
    double v;
    if (scanf("%lf", &v) != 1) return 0;
    x[i] = (tc_estimator_real)v;
  }
  return 1;
}

int main(int argc, char** argv) {
  static tc_estimator_real x[TC_ESTIMATOR_IN_SIZE], out[TC_ESTIMATOR_OUT_SIZE];
  tc_estimator_defaults(x);
  if (argc > 1 && strcmp(argv[1], "--meta") == 0) {
    printf("%s\n", tc_estimator_metadata());
    return 0;
  }
  if (argc > 1 && strcmp(argv[1], "--defaults") == 0) {
    for (int i = 0; i < TC_ESTIMATOR_IN_SIZE; ++i) printf("%.17g ", (double)x[i]);
    printf("\n");
    return 0;
  }
  if (tc_estimator_abi() != TC_ESTIMATOR_ABI) {
    fprintf(stderr, "error: library ABI %d, header ABI %d\n", tc_estimator_abi(), TC_ESTIMATOR_ABI);
    return 1;
  }
  if (argc > 2 && strcmp(argv[1], "--bench") == 0) {
    long n = atol(argv[2]);
    if (n < 1) {
      fprintf(stderr, "error: --bench N needs N >= 1\n");
      return 2;
    }
    if (!read_frame(x)) {
      tc_estimator_defaults(x);
      for (int i = TC_ESTIMATOR_IN_Q; i < TC_ESTIMATOR_IN_QD; ++i) x[i] = 0.1;
    }
    int64_t* t = malloc(sizeof(int64_t) * (size_t)n);
    if (!t) return 1;
    for (long i = 0; i < 1000; ++i) tc_estimator_step(x, out); /* warm up */
    for (long i = 0; i < n; ++i) {
      int64_t t0 = now_ns();
      tc_estimator_step(x, out);
      t[i] = now_ns() - t0;
    }
    qsort(t, (size_t)n, sizeof(int64_t), cmp_i64);
    printf("p50_ns %lld p99_ns %lld status %d\n", (long long)t[n / 2],
           (long long)t[(n * 99) / 100], (int)out[TC_ESTIMATOR_OUT_STATUS]);
    free(t);
    return 0;
  }
  while (read_frame(x)) {
    int status = tc_estimator_step(x, out);
    printf("%d", status);
    for (int i = 0; i < TC_ESTIMATOR_OUT_SIZE; ++i) printf(" %.17g", (double)out[i]);
    printf("\n");
  }
  return 0;
}
