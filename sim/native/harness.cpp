// The native harness: one Verilated board behind its two byte streams, clocked in C++.
//
// Built with the board's Verilog into a shared library (sim/native/__init__.py) and called from
// Python through ctypes with whole buffers: br_run takes a buffer of command bytes and returns
// result bytes, clocking the board as long as it takes; nothing crosses into Python per cycle.
//
// The host side of the streams is sim/drive.py's StreamHost, cycle for cycle: per clock edge it
// offers the next queued command byte unless the host idles, takes a result byte unless it
// back-pressures, with the same Stalls (per-cycle rate, bursts of burst_length cycles) drawn from
// the same generator as Python's random.Random(seed) (MT19937, seeded by init_by_array with the
// seed's 32-bit words; random() and randint() as CPython computes them).
//
// The top module's ports are named by macros (-D on the compiler's command line), so any top
// with a command byte stream in and a result byte stream out fits:
//   BR_TOP (the Verilated class), BR_CLK, BR_RST, BR_I_VALID, BR_I_READY, BR_I_PAYLOAD,
//   BR_O_VALID, BR_O_READY, BR_O_PAYLOAD; BR_RESET_REGISTERED (1: BR_RST is the port the
//   top's reset register loads, br_reset below).
#include <cstddef>
#include <cstdint>
#include <vector>

#include "native_config.h"           // the BR_ macros, written by sim/native/__init__.py
#ifndef BR_RESET_REGISTERED
#define BR_RESET_REGISTERED 0
#endif
#include "verilated.h"
#if BR_TRACE
#include "verilated_vcd_c.h"
#endif
#include BR_HEADER
#include "stalls.h"                   // Twister, Stalls

namespace {

struct Harness : HostTiming {
    VerilatedContext context;
    BR_TOP *top;
    std::vector<uint8_t> queue;             // command bytes not yet offered, from head
    size_t head = 0;
    int offer = -1;                         // the byte on the command stream, or none
    int ready = 0;                          // the host takes a result byte in the coming cycle
    bool driven = false;                    // offer and ready are decided for the coming cycle
    uint64_t cycles = 0;                    // clock edges since open
#if BR_TRACE
    VerilatedVcdC *trace = nullptr;
#endif

    Harness() : top(new BR_TOP(&context, "board")) {}
    ~Harness() {
#if BR_TRACE
        if (trace) { trace->close(); delete trace; }
#endif
        top->final();
        delete top;
    }

    // StreamHost.drive: the host decides the coming cycle as soon as the last one ended (as the
    // Amaranth testbench does, so a batch queued later is first offered a cycle later)
    void drive() {
        if (offer < 0 && head < queue.size() && !idle()) offer = queue[head++];
        ready = !pressure();
        driven = true;
    }

    // one clock cycle with the decided inputs; StreamHost.sample; returns the result byte taken or -1
    int cycle() {
        top->BR_I_VALID = offer >= 0;
        top->BR_I_PAYLOAD = offer >= 0 ? offer : 0;
        top->BR_O_READY = ready;
        top->BR_CLK = 0;
        top->eval();
        int cready = top->BR_I_READY, rvalid = top->BR_O_VALID, rpayload = top->BR_O_PAYLOAD;
        edge();
        if (offer >= 0 && cready) offer = -1;
        return rvalid && ready ? rpayload : -1;
    }

    // the rising edge after the inputs were set and evaluated with the clock low
    void edge() {
#if BR_TRACE
        if (trace) trace->dump(2 * cycles);
#endif
        top->BR_CLK = 1;
        top->eval();
#if BR_TRACE
        if (trace) trace->dump(2 * cycles + 1);
#endif
        cycles++;
    }
};

}  // namespace

extern "C" {

// A board with host timing (idle, back-pressure: rate, burst probability, burst length min and
// max) seeded by the 32-bit words ``key`` of the seed, as random.Random(seed). ``vcd``: a
// waveform file (a build with BR_TRACE) or null.
void *br_open(const uint32_t *key, size_t key_words,
              double idle_rate, double idle_burst, uint32_t idle_lo, uint32_t idle_hi,
              double bp_rate, double bp_burst, uint32_t bp_lo, uint32_t bp_hi, const char *vcd) {
    Harness *h = new Harness();
    h->seed(key, key_words, idle_rate, idle_burst, idle_lo, idle_hi, bp_rate, bp_burst, bp_lo, bp_hi);
#if BR_TRACE
    if (vcd) {
        h->context.traceEverOn(true);
        h->trace = new VerilatedVcdC;
        h->top->trace(h->trace, 99);
        h->trace->open(vcd);
    }
#else
    (void)vcd;
#endif
    h->top->BR_RST = 0;
    h->top->BR_I_VALID = 0;
    h->top->BR_O_READY = 0;
    h->top->BR_CLK = 0;
    h->top->eval();
    return h;
}

void br_close(void *handle) { delete static_cast<Harness *>(handle); }

uint64_t br_cycles(void *handle) { return static_cast<Harness *>(handle)->cycles; }

// The board's synchronous reset for one clock cycle (streams idle), after the cycle the host
// already decided; queued command bytes are dropped, and so is a result byte of that cycle.
// With BR_RESET_REGISTERED the board's rst is a register loaded from the BR_RST port at each
// edge (sim/native/share.py, register_reset): the port is raised in the cycle before the reset
// cycle, the decided one (or, if none was decided since br_open, an extra edge with the streams
// idle that br_cycles and the waveform do not count: the board's state before its first reset
// is the initial one either way).
void br_reset(void *handle) {
    Harness *h = static_cast<Harness *>(handle);
    h->queue.clear();
    h->head = 0;
    int offered = h->offer;
    h->offer = -1;
    if (h->driven) {                        // the host's offer stands on the wire until the edge
        h->top->BR_I_VALID = offered >= 0;
        h->top->BR_I_PAYLOAD = offered >= 0 ? offered : 0;
        h->top->BR_O_READY = h->ready;
        h->top->BR_RST = BR_RESET_REGISTERED;
        h->top->BR_CLK = 0;
        h->top->eval();
        h->edge();
    }
#if BR_RESET_REGISTERED
    else {
        h->top->BR_I_VALID = 0;
        h->top->BR_O_READY = 0;
        h->top->BR_RST = 1;
        h->top->BR_CLK = 0;
        h->top->eval();
        h->top->BR_CLK = 1;
        h->top->eval();
    }
    h->top->BR_RST = 0;
#else
    h->top->BR_RST = 1;
#endif
    h->top->BR_I_VALID = 0;
    h->top->BR_O_READY = 0;
    h->top->BR_CLK = 0;
    h->top->eval();
    h->edge();
    h->top->BR_RST = 0;
    h->drive();
}

// Queue ``count`` command bytes, then clock the board until ``want`` result bytes came (0), or
// ``capacity`` came (1: call again for the rest), or nothing moved on either stream for
// ``patience`` cycles while no command byte was left to offer (2). Command bytes not yet taken
// stay queued for the next call. The result bytes go to ``out``; ``*got`` says how many.
int br_run(void *handle, const uint8_t *commands, size_t count, uint8_t *out, size_t capacity,
           size_t want, uint64_t patience, size_t *got) {
    Harness *h = static_cast<Harness *>(handle);
    if (h->head == h->queue.size()) {
        h->queue.clear();
        h->head = 0;
    }
    h->queue.insert(h->queue.end(), commands, commands + count);
    if (!h->driven) h->drive();
    size_t received = 0;
    uint64_t quiet = 0;
    int status;
    for (;;) {
        if (received >= want) { status = 0; break; }
        if (received == capacity) { status = 1; break; }
        if (h->offer < 0 && h->head == h->queue.size() && quiet > patience) { status = 2; break; }
        bool offered = h->offer >= 0;
        int byte = h->cycle();
        quiet = (offered && h->offer < 0) || byte >= 0 ? 0 : quiet + 1;
        if (byte >= 0) out[received++] = (uint8_t)byte;
        h->drive();
    }
    *got = received;
    return status;
}

}  // extern "C"
