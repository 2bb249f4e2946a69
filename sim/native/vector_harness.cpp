// The vector harness: a Verilated stream component (an input stream ``i`` and an output stream
// ``o`` of payloads of any width), clocked in C++, one payload a cycle each way at most.
//
// Built with the component's Verilog into a shared library (sim/native/vectors.py) and called
// from Python through ctypes with whole buffers of payloads, BR_I_BYTES bytes each in and
// BR_O_BYTES out, least significant byte first. The host offers the next payload unless it
// idles and takes an output unless it back-pressures, with the Stalls of harness.cpp (the same
// generator, seeded the same way).
//
// Port macros (native_config.h): BR_TOP, BR_CLK, BR_RST, BR_I_VALID, BR_I_READY, BR_I_PAYLOAD,
// BR_O_VALID, BR_O_READY, BR_O_PAYLOAD, BR_I_BYTES, BR_O_BYTES.
#include <cstddef>
#include <cstdint>
#include <cstring>

#include "native_config.h"
#include "verilated.h"
#include BR_HEADER
#include "stalls.h"                   // Twister, Stalls

namespace {

// a port of up to 64 bits is an integer, a wider one a VlWide of 32-bit words (little-endian host)
template <typename T> void put(T &port, const uint8_t *p) {
    T v = 0;
    std::memcpy(&v, p, BR_I_BYTES);
    port = v;
}
template <std::size_t W> void put(VlWide<W> &port, const uint8_t *p) {
    EData *words = port;
    std::memset(words, 0, sizeof(EData) * W);
    std::memcpy(words, p, BR_I_BYTES);
}
template <typename T> void get(const T &port, uint8_t *p) {
    T v = port;
    std::memcpy(p, &v, BR_O_BYTES);
}
template <std::size_t W> void get(const VlWide<W> &port, uint8_t *p) {
    const EData *words = port;
    std::memcpy(p, words, BR_O_BYTES);
}

struct Vectors : HostTiming {
    VerilatedContext context;
    BR_TOP *top;
    uint64_t cycles = 0;

    Vectors() : top(new BR_TOP(&context, "board")) {}
    ~Vectors() {
        top->final();
        delete top;
    }

    void edge() {
        top->BR_CLK = 1;
        top->eval();
        cycles++;
    }
};

}  // namespace

extern "C" {

// A component with host timing as harness.cpp's br_open (without a waveform).
void *bv_open(const uint32_t *key, size_t key_words,
              double idle_rate, double idle_burst, uint32_t idle_lo, uint32_t idle_hi,
              double bp_rate, double bp_burst, uint32_t bp_lo, uint32_t bp_hi) {
    Vectors *h = new Vectors();
    h->seed(key, key_words, idle_rate, idle_burst, idle_lo, idle_hi, bp_rate, bp_burst, bp_lo, bp_hi);
    h->top->BR_RST = 0;                     // registers start at their Verilog initial values
    h->top->BR_I_VALID = 0;
    h->top->BR_O_READY = 0;
    h->top->BR_CLK = 0;
    h->top->eval();
    return h;
}

void bv_close(void *handle) { delete static_cast<Vectors *>(handle); }

uint64_t bv_cycles(void *handle) { return static_cast<Vectors *>(handle)->cycles; }

// Send ``count`` payloads and clock until ``count`` outputs came (0), or nothing moved on
// either stream for ``patience`` cycles (2). The outputs go to ``out``; ``*got`` says how many.
int bv_run(void *handle, const uint8_t *in, size_t count, uint8_t *out, uint64_t patience, size_t *got) {
    Vectors *h = static_cast<Vectors *>(handle);
    BR_TOP *top = h->top;
    size_t sent = 0, received = 0;
    bool offered = false;
    uint64_t quiet = 0;
    while (received < count) {
        if (!offered && sent < count && !h->idle()) {
            put(top->BR_I_PAYLOAD, in + sent * BR_I_BYTES);
            offered = true;
        }
        bool ready = !h->pressure();
        top->BR_I_VALID = offered;
        top->BR_O_READY = ready;
        top->BR_CLK = 0;
        top->eval();
        bool took = offered && top->BR_I_READY, gave = ready && top->BR_O_VALID;
        if (gave) get(top->BR_O_PAYLOAD, out + received++ * BR_O_BYTES);
        h->edge();
        if (took) {
            sent++;
            offered = false;
        }
        quiet = took || gave ? 0 : quiet + 1;
        if (quiet > patience) break;
    }
    *got = received;
    return received == count ? 0 : 2;
}

}  // extern "C"
