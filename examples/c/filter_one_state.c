/* Filter one state with a reach safety filter compiled to C: no Python, no torch, no ONNX Runtime.

   The filter comes from `reach export SOURCE --out f.onnx --c filter.c` (reach_runtime.native). Its
   reach_filter_checked makes the runtime's checks (NaN or inf in a state, time or nominal input; a
   time-to-go outside the range the value function covers) and refuses a batch the value function
   cannot be trusted on, so this program fails closed as reach_runtime.Filter does.

   usage: filter_one_state T X1 .. Xn U1 .. Um     (n = REACH_STATE_DIM, m = REACH_CONTROL_DIM)
   build: cc -O3 -march=native -fno-math-errno -fno-trapping-math -I BUILD filter_one_state.c -lm
          (BUILD holds filter.c; build_and_run.sh does all of it) */
#include <stdio.h>
#include <stdlib.h>

#include "filter.c"

static const char *why(int status) {
  switch (status) {
    case REACH_BAD_INPUT: return "a state, time or nominal input is NaN or inf";
    case REACH_TIME_OUT_OF_RANGE: return "the time-to-go lies outside the range the value function covers";
    case REACH_UNTRUSTED: return "the value function returned a non-finite value, gradient or optimal input";
    case REACH_INDEX_OUT_OF_RANGE: return "a computed index fell outside its tensor";
    default: return "unknown status";
  }
}

int main(int argc, char **argv) {
  if (argc != 2 + REACH_STATE_DIM + REACH_CONTROL_DIM) {
    fprintf(stderr, "usage: %s T X1..X%d U1..U%d\n", argv[0], REACH_STATE_DIM, REACH_CONTROL_DIM);
    return 2;
  }
  float t = strtof(argv[1], NULL), x[REACH_STATE_DIM], u[REACH_CONTROL_DIM];
  for (int k = 0; k < REACH_STATE_DIM; ++k) x[k] = strtof(argv[2 + k], NULL);
  for (int k = 0; k < REACH_CONTROL_DIM; ++k) u[k] = strtof(argv[2 + REACH_STATE_DIM + k], NULL);

  float control[REACH_CONTROL_DIM], value, gradient[REACH_STATE_DIM];
  unsigned char intervened, infeasible, outside_domain, untrusted;
  int status = reach_filter_checked(1, x, &t, u, control, &value, gradient, &intervened, &infeasible,
                                    &outside_domain, &untrusted);
  if (status != REACH_OK) {
    printf("refused: %s (status %d)\n", why(status), status);
    return 3; /* the caller applies its own fallback: no decision is used */
  }
  printf("value: %.7g\n", value);
  printf("control:");
  for (int k = 0; k < REACH_CONTROL_DIM; ++k) printf(" %.7g", control[k]);
  printf("\nflags: intervened=%d infeasible=%d outside_domain=%d\n", intervened, infeasible, outside_domain);
  return 0;
}
