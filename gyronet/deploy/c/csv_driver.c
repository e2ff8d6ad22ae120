/* csv_driver.c: run a generated gyronet compensator over a file of samples, on a host.
 *
 *     cc -std=c99 -O2 -I DIR csv_driver.c DIR/gyronet_compensator.c -lm -o driver
 *     ./driver in.csv out.csv [repeat [still_s]]
 *
 * in.csv: a gyronet recording whose columns begin time_s,temp_c,gyro_x_dps,gyro_y_dps,gyro_z_dps[,aux...]
 * (the simulator's order; nan allowed): the "#" lines above the header are skipped, the header is checked and
 * later columns are ignored. out.csv: gyro_x_dps,gyro_y_dps,gyro_z_dps,flags,drift_sigma_x_dps,drift_sigma_y_dps,
 * drift_sigma_z_dps per sample. The step loop runs
 * `repeat` times from gyronet_init (default 1) and its best time per sample goes to stderr as
 * "ns_per_sample=..."; still_s > 0 calls gyronet_start_offset first.
 */
#define _POSIX_C_SOURCE 199309L
#ifdef GYRONET_TRAP_FP /* -DGYRONET_TRAP_FP (glibc): an invalid operation, a division by zero or an overflow stops it */
#define _GNU_SOURCE
#include <fenv.h>
#endif
#include <stdio.h>
#include <stdlib.h>
#include <string.h>
#include <time.h>

#include "gyronet_compensator.h"

#define N_COLUMNS (5 + GYRONET_N_AUX)
#define FIRST_COLUMNS "time_s,temp_c,gyro_x_dps,gyro_y_dps,gyro_z_dps"

static double now_s(void)
{
    struct timespec t;
    clock_gettime(CLOCK_MONOTONIC, &t);
    return (double)t.tv_sec + 1e-9 * (double)t.tv_nsec;
}

int main(int argc, char **argv)
{
    FILE *in, *out;
    double *rows = NULL, best_s = 1e300, start_s;
    float *results, *sigmas, gyro[3];
    int *flags, repeat = argc > 3 ? atoi(argv[3]) : 1, c, r;
    double still_s = argc > 4 ? atof(argv[4]) : 0.0;
    size_t n = 0, capacity = 0, i;
    char line[4096];
    gyronet_state state;
#if GYRONET_N_AUX > 0
    float aux[GYRONET_N_AUX];
#endif
#ifdef GYRONET_TRAP_FP
    feenableexcept(FE_INVALID | FE_DIVBYZERO | FE_OVERFLOW);
#endif
    if (argc < 3 || !(in = fopen(argv[1], "r"))) {
        fprintf(stderr, "usage: %s in.csv out.csv [repeat [still_s]]\n", argv[0]);
        return 2;
    }
    do {
        if (!fgets(line, sizeof line, in)) {
            fprintf(stderr, "%s: no header line\n", argv[1]);
            return 2;
        }
    } while (line[0] == '#');
    if (strncmp(line, FIRST_COLUMNS, strlen(FIRST_COLUMNS)) != 0) {
        fprintf(stderr, "%s: the columns must begin " FIRST_COLUMNS "\n", argv[1]);
        return 2;
    }
    while (fgets(line, sizeof line, in)) {
        char *p = line, *end;
        if (n == capacity) {
            capacity = capacity ? 2 * capacity : 4096;
            rows = realloc(rows, capacity * N_COLUMNS * sizeof *rows);
        }
        for (c = 0; c < N_COLUMNS; ++c) {
            rows[n * N_COLUMNS + c] = strtod(p, &end);
            p = end + (*end == ',');
        }
        ++n;
    }
    fclose(in);
    results = malloc((n ? n : 1) * 3 * sizeof *results);
    flags = malloc((n ? n : 1) * sizeof *flags);
    sigmas = malloc((n ? n : 1) * 3 * sizeof *sigmas);
    for (r = 0; r < (repeat > 0 ? repeat : 1); ++r) {
        gyronet_init(&state);
        if (still_s > 0.0) {
            gyronet_start_offset(&state, still_s, NULL);
        }
        start_s = now_s();
        for (i = 0; i < n; ++i) {
            const double *row = rows + i * N_COLUMNS;
            gyro[0] = (float)row[2];
            gyro[1] = (float)row[3];
            gyro[2] = (float)row[4];
#if GYRONET_N_AUX > 0
            for (c = 0; c < GYRONET_N_AUX; ++c) {
                aux[c] = (float)row[5 + c];
            }
            flags[i] = gyronet_step(&state, row[0], (float)row[1], gyro, aux, results + 3 * i);
#else
            flags[i] = gyronet_step(&state, row[0], (float)row[1], gyro, results + 3 * i);
#endif
            sigmas[3 * i] = state.drift_sigma_dps[0];
            sigmas[3 * i + 1] = state.drift_sigma_dps[1];
            sigmas[3 * i + 2] = state.drift_sigma_dps[2];
        }
        start_s = now_s() - start_s;
        best_s = start_s < best_s ? start_s : best_s;
    }
    fprintf(stderr, "ns_per_sample=%.2f samples=%lu\n", n ? 1e9 * best_s / (double)n : 0.0, (unsigned long)n);
    if (!(out = fopen(argv[2], "w"))) {
        return 2;
    }
    fprintf(out, "gyro_x_dps,gyro_y_dps,gyro_z_dps,flags,drift_sigma_x_dps,drift_sigma_y_dps,drift_sigma_z_dps\n");
    for (i = 0; i < n; ++i) {
        fprintf(out, "%.9g,%.9g,%.9g,%d,%.9g,%.9g,%.9g\n", (double)results[3 * i], (double)results[3 * i + 1],
                (double)results[3 * i + 2], flags[i], (double)sigmas[3 * i], (double)sigmas[3 * i + 1],
                (double)sigmas[3 * i + 2]);
    }
    fclose(out);
    free(rows);
    free(results);
    free(flags);
    free(sigmas);
    return 0;
}
