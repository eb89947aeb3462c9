#!/usr/bin/env bash
# What a fresh page costs this machine (README, "Stop 52"): a C loop faults in
# 200 MB of fresh anonymous memory one 4 KiB page at a time, then rewrites the
# same memory once faulted in; three rounds. Needs a C compiler (cc).
#
# usage: benches/fault_cost.sh
set -eu
work=$(mktemp -d)
trap 'rm -rf "$work"' EXIT
cat > "$work/fault_cost.c" <<'C'
#include <stdio.h>
#include <string.h>
#include <sys/mman.h>
#include <time.h>
static double ms(struct timespec a, struct timespec b) {
    return (b.tv_sec - a.tv_sec) * 1e3 + (b.tv_nsec - a.tv_nsec) / 1e6;
}
int main(void) {
    const size_t n = 200u << 20, page = 4096;
    for (int round = 0; round < 3; round++) {
        char *p = mmap(0, n, PROT_READ | PROT_WRITE, MAP_PRIVATE | MAP_ANONYMOUS, -1, 0);
        if (p == MAP_FAILED) return 1;
        struct timespec a, b, c;
        clock_gettime(CLOCK_MONOTONIC, &a);
        for (size_t i = 0; i < n; i += page) p[i] = 1;
        clock_gettime(CLOCK_MONOTONIC, &b);
        memset(p, 2, n);
        clock_gettime(CLOCK_MONOTONIC, &c);
        printf("fault in 200 MB: %6.1f ms (%.2f us a page); rewrite it: %5.1f ms\n",
               ms(a, b), ms(a, b) * 1e3 / (n / page), ms(b, c));
        munmap(p, n);
    }
    return 0;
}
C
cc -O2 "$work/fault_cost.c" -o "$work/fault_cost"
"$work/fault_cost"
