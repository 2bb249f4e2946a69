// The host's random timing, shared by the native harnesses (harness.cpp, vector_harness.cpp):
// Python's random.Random (MT19937 as CPython's _randommodule.c, seeded by init_by_array with the
// seed's 32-bit words; random() and randint() as CPython computes them) and sim/drive.py's Stalls.
#pragma once
#include <cstddef>
#include <cstdint>

namespace {

// MT19937 as CPython's _randommodule.c.
struct Twister {
    static const int N = 624, M = 397;
    uint32_t mt[N];
    int mti = N + 1;

    void init_genrand(uint32_t s) {
        mt[0] = s;
        for (mti = 1; mti < N; mti++)
            mt[mti] = 1812433253U * (mt[mti - 1] ^ (mt[mti - 1] >> 30)) + mti;
    }
    void init_by_array(const uint32_t *key, size_t len) {
        init_genrand(19650218U);
        size_t i = 1, j = 0;
        for (size_t k = (N > len ? N : len); k; k--) {
            mt[i] = (mt[i] ^ ((mt[i - 1] ^ (mt[i - 1] >> 30)) * 1664525U)) + key[j] + (uint32_t)j;
            i++; j++;
            if (i >= (size_t)N) { mt[0] = mt[N - 1]; i = 1; }
            if (j >= len) j = 0;
        }
        for (size_t k = N - 1; k; k--) {
            mt[i] = (mt[i] ^ ((mt[i - 1] ^ (mt[i - 1] >> 30)) * 1566083941U)) - (uint32_t)i;
            i++;
            if (i >= (size_t)N) { mt[0] = mt[N - 1]; i = 1; }
        }
        mt[0] = 0x80000000U;
    }
    uint32_t next() {
        static const uint32_t mag01[2] = {0x0U, 0x9908b0dfU};
        uint32_t y;
        if (mti >= N) {
            int kk;
            for (kk = 0; kk < N - M; kk++) {
                y = (mt[kk] & 0x80000000U) | (mt[kk + 1] & 0x7fffffffU);
                mt[kk] = mt[kk + M] ^ (y >> 1) ^ mag01[y & 0x1U];
            }
            for (; kk < N - 1; kk++) {
                y = (mt[kk] & 0x80000000U) | (mt[kk + 1] & 0x7fffffffU);
                mt[kk] = mt[kk + (M - N)] ^ (y >> 1) ^ mag01[y & 0x1U];
            }
            y = (mt[N - 1] & 0x80000000U) | (mt[0] & 0x7fffffffU);
            mt[N - 1] = mt[M - 1] ^ (y >> 1) ^ mag01[y & 0x1U];
            mti = 0;
        }
        y = mt[mti++];
        y ^= (y >> 11);
        y ^= (y << 7) & 0x9d2c5680U;
        y ^= (y << 15) & 0xefc60000U;
        y ^= (y >> 18);
        return y;
    }
    double random() {                       // random.random()
        uint32_t a = next() >> 5, b = next() >> 6;
        return (a * 67108864.0 + b) * (1.0 / 9007199254740992.0);
    }
    uint32_t below(uint32_t n) {            // random._randbelow_with_getrandbits (n < 2**32)
        int k = 0;
        for (uint32_t v = n; v; v >>= 1) k++;
        uint32_t r = next() >> (32 - k);
        while (r >= n) r = next() >> (32 - k);
        return r;
    }
};

// sim/drive.py's Stalls.
struct Stalls {
    double rate = 0, burst = 0;
    uint32_t lo = 16, hi = 256, left = 0;
    Twister *rng = nullptr;

    bool operator()() {
        if (rate == 0.0 && burst == 0.0) return false;
        if (left) { left--; return true; }
        if (burst != 0.0 && rng->random() < burst) {
            left = lo + rng->below(hi - lo + 1) - 1;
            return true;
        }
        return rate != 0.0 && rng->random() < rate;
    }
};

// The host's timing on both streams from one generator, as StreamHost draws it.
struct HostTiming {
    Twister rng;
    Stalls idle, pressure;

    void seed(const uint32_t *key, size_t key_words,
              double idle_rate, double idle_burst, uint32_t idle_lo, uint32_t idle_hi,
              double bp_rate, double bp_burst, uint32_t bp_lo, uint32_t bp_hi) {
        rng.init_by_array(key, key_words);
        idle = Stalls{idle_rate, idle_burst, idle_lo, idle_hi, 0, &rng};
        pressure = Stalls{bp_rate, bp_burst, bp_lo, bp_hi, 0, &rng};
    }
};

}  // namespace
