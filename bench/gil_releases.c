/* bench/bench_gil_releases.py's LD_PRELOAD shim: counts the PyEval_SaveThread calls (each a release of the
   interpreter lock: numpy's NPY_BEGIN_THREADS, a BLAS call, numba's nogil, ctypes' CDLL) that the armed thread makes
   while armed (arm/disarm nest). */
#define _GNU_SOURCE
#include <dlfcn.h>
#include <pthread.h>
typedef void *(*save_t)(void);
static save_t real_save;
static pthread_t armed_thread;
static volatile int depth;
static long count;
void *PyEval_SaveThread(void) {
    if (!real_save) real_save = (save_t)dlsym(RTLD_NEXT, "PyEval_SaveThread");
    if (depth > 0 && pthread_equal(pthread_self(), armed_thread)) count++;
    return real_save();
}
void gilcount_arm(void) { armed_thread = pthread_self(); depth++; }
void gilcount_disarm(void) { depth--; }
long gilcount_get(void) { return count; }
