/* A 1 kHz control loop around an snds C export, measuring its deadline misses and jitter.
 *
 *   snds export runs/Sine --format c --out examples/c/policy.h
 *   gcc -std=c99 -O2 -Wall examples/c/control_loop.c examples/c/policy.c -lm -o loop
 *   ./loop 60 1000        # seconds, Hz; prints one JSON line
 *
 * The robot is an ideal integrator of the command (it reaches the step's `next` state), started
 * 3 extents from the target (a model with a phase takes its start state's phase from
 * snds_start_state) and put back there when it arrives (within 1 % of the extent) or after
 * 30 extents at the top speed (10x the time to come straight back at that speed), so the policy is evaluated far from and near the data; the line reports how many of
 * these runs arrived and their median time to arrive. Each period sleeps until its absolute
 * deadline (clock_nanosleep), reads the
 * clock (wake-up latency: the jitter), computes the guarded step (compute time) and counts a
 * miss when the step ends after the next deadline. No allocation in the loop. POSIX. */
#define _POSIX_C_SOURCE 200112L
#include <stdio.h>
#include <stdlib.h>
#include <time.h>
#include <math.h>
#include "policy.h"

#define MAX_PERIODS 600000

static double seconds(const struct timespec *t) { return (double)t->tv_sec + 1e-9 * (double)t->tv_nsec; }

static int compare(const void *a, const void *b) {
    double x = *(const double *)a, y = *(const double *)b;
    return (x > y) - (x < y);
}

static double percentile(double *values, long count, double p) {
    qsort(values, (size_t)count, sizeof(double), compare);
    return values[(long)(p * (double)(count - 1))];
}

static double wake[MAX_PERIODS], compute[MAX_PERIODS], arrival[MAX_PERIODS];

/* The distance between two states' positions. */
static double distance(const double *a, const double *b) {
    double sum = 0.0;
    int k;
    for (k = 0; k < SNDS_POSITION_DIM; ++k) sum += (a[k] - b[k]) * (a[k] - b[k]);
    return sqrt(sum);
}

int main(int argc, char **argv) {
    double duration = argc > 1 ? atof(argv[1]) : 60.0, rate = argc > 2 ? atof(argv[2]) : 1000.0;
    double period = 1.0 / rate, x[SNDS_STATE_DIM], start[SNDS_STATE_DIM] = SNDS_TARGET;
    double command[SNDS_VELOCITY_DIM], next[SNDS_STATE_DIM], target[SNDS_STATE_DIM] = SNDS_TARGET;
    double since = 0.0, limit = 30.0 * SNDS_EXTENT / SNDS_TOP_SPEED;
    long periods = (long)(duration * rate), misses = 0, i, runs = 0, arrived = 0;
    int k;
    struct timespec deadline, now, done;
    if (periods > MAX_PERIODS) periods = MAX_PERIODS;
    for (k = 0; k < SNDS_POSITION_DIM; ++k) start[k] += 3.0 * SNDS_EXTENT * (k % 2 ? -1.0 : 1.0);
#ifdef SNDS_START_COUNT
    {
        double base[SNDS_STATE_DIM];
        for (k = 0; k < SNDS_STATE_DIM; ++k) base[k] = start[k];
        snds_start_state(base, start); /* the phase a new start takes */
    }
#endif
    for (k = 0; k < SNDS_STATE_DIM; ++k) x[k] = start[k];
    clock_gettime(CLOCK_MONOTONIC, &deadline);
    for (i = 0; i < periods; ++i) {
        deadline.tv_nsec += (long)(period * 1e9);
        while (deadline.tv_nsec >= 1000000000L) { deadline.tv_nsec -= 1000000000L; deadline.tv_sec += 1; }
        clock_nanosleep(CLOCK_MONOTONIC, TIMER_ABSTIME, &deadline, NULL);
        clock_gettime(CLOCK_MONOTONIC, &now);
        wake[i] = seconds(&now) - seconds(&deadline);
        snds_step(x, period, SNDS_MAX_SPEED, command, next);
        for (k = 0; k < SNDS_STATE_DIM; ++k) x[k] = next[k];
        since += period;
        if (distance(x, target) <= 0.01 * SNDS_EXTENT || since >= limit) {
            if (since < limit) arrival[arrived++] = since;
            for (k = 0; k < SNDS_STATE_DIM; ++k) x[k] = start[k];
            since = 0.0;
            ++runs;
        }
        clock_gettime(CLOCK_MONOTONIC, &done);
        compute[i] = seconds(&done) - seconds(&now);
        if (seconds(&done) > seconds(&deadline) + period) ++misses;
    }
    printf("{\"rate_hz\": %.0f, \"periods\": %ld, \"deadline_misses\": %ld, "
           "\"wake_latency_us\": {\"median\": %.2f, \"p99\": %.2f, \"p999\": %.2f, \"max\": %.2f}, ",
           rate, periods, misses, 1e6 * percentile(wake, periods, 0.5),
           1e6 * percentile(wake, periods, 0.99), 1e6 * percentile(wake, periods, 0.999),
           1e6 * percentile(wake, periods, 1.0));
    printf("\"step_us\": {\"median\": %.2f, \"p99\": %.2f, \"max\": %.2f}, "
           "\"runs\": %ld, \"arrived\": %ld, \"median_arrival_s\": %.3g}\n",
           1e6 * percentile(compute, periods, 0.5), 1e6 * percentile(compute, periods, 0.99),
           1e6 * percentile(compute, periods, 1.0), runs, arrived,
           arrived ? percentile(arrival, arrived, 0.5) : -1.0);
    return 0;
}
