/* The wake-up floor of this machine, for bench/fieldbus.py: what the kernel alone gives a periodic
 * thread, without Python. Like cyclictest: sleep to absolute deadlines with clock_nanosleep
 * (TIMER_ABSTIME), measure how late each wake-up is.
 *
 *   rt_floor PERIOD_US CYCLES PRIORITY CPU_LATENCY_US [LATENESS_FILE]
 *
 * PRIORITY > 0: SCHED_FIFO at that priority. CPU_LATENCY_US >= 0: hold a PM QoS request on
 * /dev/cpu_dma_latency for the run. Prints: p50 p99 p999 max (us) and the cycles later than half a
 * period, as one line of numbers. LATENESS_FILE: every wake-up's lateness (ns), one a line, in
 * order (bench/fieldbus_stress.py takes its per-second p99.9 from it: is the host taking CPUs away?),
 * after a first line "# start_ns T": the CLOCK_MONOTONIC time the i-th wake-up is due after, (i + 1)
 * periods (the bench runs it beside each case and takes the wake-ups of the case's window). SIGTERM
 * ends the run early, with the wake-ups so far written and counted.
 */
#define _GNU_SOURCE
#include <fcntl.h>
#include <sched.h>
#include <signal.h>
#include <stdint.h>
#include <stdio.h>
#include <stdlib.h>
#include <time.h>
#include <unistd.h>

static volatile sig_atomic_t stop;

static void on_term(int sig) {
    (void)sig;
    stop = 1;
}

static int cmp(const void *a, const void *b) {
    int64_t x = *(const int64_t *)a, y = *(const int64_t *)b;
    return (x > y) - (x < y);
}

int main(int argc, char **argv) {
    if (argc != 5 && argc != 6) {
        fprintf(stderr, "usage: rt_floor PERIOD_US CYCLES PRIORITY CPU_LATENCY_US [LATENESS_FILE]\n");
        return 2;
    }
    int64_t period = atoll(argv[1]) * 1000;
    int n = atoi(argv[2]), prio = atoi(argv[3]), latency = atoi(argv[4]);
    if (period <= 0 || n <= 0) return 2;
    if (prio > 0) {
        struct sched_param sp = {.sched_priority = prio};
        if (sched_setscheduler(0, SCHED_FIFO, &sp) != 0) perror("rt_floor: SCHED_FIFO refused");
    }
    int qos = -1;
    if (latency >= 0) {
        qos = open("/dev/cpu_dma_latency", O_WRONLY);
        int32_t v = latency;
        if (qos < 0 || write(qos, &v, sizeof v) != sizeof v) perror("rt_floor: no CPU latency request");
    }
    int64_t *late = malloc(sizeof(int64_t) * (size_t)n);
    if (!late) return 1;
    struct sigaction sa = {.sa_handler = on_term};
    sigemptyset(&sa.sa_mask);
    sigaction(SIGTERM, &sa, NULL);
    struct timespec t, now;
    clock_gettime(CLOCK_MONOTONIC, &t);
    int64_t start_ns = t.tv_sec * 1000000000LL + t.tv_nsec;
    int done = 0;
    while (done < n && !stop) {
        t.tv_nsec += period;
        while (t.tv_nsec >= 1000000000L) { t.tv_nsec -= 1000000000L; t.tv_sec++; }
        while (clock_nanosleep(CLOCK_MONOTONIC, TIMER_ABSTIME, &t, NULL) != 0 && !stop) {
        }
        if (stop) break;  /* a wake-up by the signal is not a timer's */
        clock_gettime(CLOCK_MONOTONIC, &now);
        late[done++] = (now.tv_sec - t.tv_sec) * 1000000000LL + (now.tv_nsec - t.tv_nsec);
    }
    n = done;
    if (n == 0) return 1;
    if (qos >= 0) close(qos);
    if (argc == 6) {
        FILE *f = fopen(argv[5], "w");
        if (!f) {
            perror("rt_floor: lateness file");
            return 1;
        }
        fprintf(f, "# start_ns %lld\n", (long long)start_ns);
        for (int i = 0; i < n; i++) fprintf(f, "%lld\n", (long long)late[i]);
        fclose(f);
    }
    int missed = 0;
    for (int i = 0; i < n; i++) missed += late[i] > period / 2;
    qsort(late, (size_t)n, sizeof(int64_t), cmp);
    printf("%.0f %.0f %.0f %.0f %d\n", late[n / 2] / 1e3, late[(int64_t)n * 99 / 100] / 1e3,
           late[(int64_t)n * 999 / 1000] / 1e3, late[n - 1] / 1e3, missed);
    free(late);
    return 0;
}
