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
//   top's reset register loads, br_reset below); BR_RECORDS (1: the top also takes whole command
//   records on BR_R_VALID, BR_R_READY, BR_R_PAYLOAD, below).
//
// Records (br_records): the byte link costs the board no board cycles but about five clock cycles
// for each (a command runs when its last byte arrived), so with a quiet host (no idle, no
// back-pressure) the harness can cut the queued bytes into commands itself and hand the board one
// whole command record a clock cycle, as the core's deframer would have made it (rtl/core.py,
// ``records``): the same board cycles and results in fewer clock cycles. A header whose opcode the
// table does not know (the ray commands) sends that byte and everything after it, until the
// next reset, over the byte stream.
#include <cstddef>
#include <cstdint>
#include <cstring>
#include <vector>

#include "native_config.h"           // the BR_ macros, written by sim/native/__init__.py
#ifndef BR_RESET_REGISTERED
#define BR_RESET_REGISTERED 0
#endif
#ifndef BR_RECORDS
#define BR_RECORDS 0
#endif
#include "verilated.h"
#if BR_TRACE
#include "verilated_vcd_c.h"
#endif
#include BR_HEADER
#ifdef BR_ROOT_HEADER
#include BR_ROOT_HEADER             // the clock's previous value (br_single_eval)
#endif
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
    // records: per header (op, LOAD_POINTS count) its payload bytes (-1: unknown) and its record's
    // argument bits; the op's bits below the argument
    bool records = false, bytes_only = false;
    int payload[64], arg_bits[64], arg_offset = 0;
    bool record_offered = false;
    bool incomplete = false;                // the queue ends in the middle of the next record
    uint32_t record[64];                    // the record on the record stream (words of 32 bits)
    // one eval a clock cycle (br_single_eval): the ports sampled before the edge are registered
    // (set by the previous edge's eval), so the eval with the clock low is skipped and the edge's
    // eval, whose input phase comes first, sees the cycle's inputs
    bool single_eval = false;
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
        incomplete = false;
        if (records && !bytes_only && !record_offered && head < queue.size()) next_record();
        if ((!records || bytes_only) && offer < 0 && head < queue.size() && !idle()) offer = queue[head++];
        ready = !pressure();
        driven = true;
    }

    // the command at the queue's head as a record, once all its bytes are queued: op in the low
    // bits, the payload from bit arg_offset, cut to the argument's bits (the deframer's ``arg``)
    void next_record() {
        uint8_t header = queue[head];
        int kind = (header & 15) * 4 + (header >> 4 & 3);
        if (payload[kind] < 0) { bytes_only = true; return; }
        size_t n = payload[kind];
        if (queue.size() - head < 1 + n) { incomplete = true; return; }
        std::memset(record, 0, sizeof record);
        record[0] = header & ((1u << arg_offset) - 1);
        for (size_t i = 0; i < n; i++) {
            size_t bit = arg_offset + 8 * i;
            uint32_t v = queue[head + 1 + i];
            record[bit / 32] |= v << (bit % 32);
            if (bit % 32 > 24) record[bit / 32 + 1] |= v >> (32 - bit % 32);
        }
        int end = arg_offset + arg_bits[kind];               // clear the bits past the argument
        for (int b = end; b < 64 * 32; b++) {
            if (b % 32 == 0) { std::memset(record + b / 32, 0, sizeof(uint32_t) * (64 - b / 32)); break; }
            record[b / 32] &= ~(1u << (b % 32));
        }
        head += 1 + n;
        record_offered = true;
    }

    // nothing on either command stream and nothing more to offer until more bytes are queued
    bool starved() const { return offer < 0 && !record_offered && (head == queue.size() || incomplete); }

    // one clock cycle with the decided inputs; StreamHost.sample; returns the result byte taken or -1
    // the decided cycle's inputs on the ports
    void inputs() {
        top->BR_I_VALID = offer >= 0;
        top->BR_I_PAYLOAD = offer >= 0 ? offer : 0;
        top->BR_O_READY = ready;
#if BR_RECORDS
        top->BR_R_VALID = record_offered;
        if (record_offered) {
            for (size_t i = 0; i < sizeof(top->BR_R_PAYLOAD) / sizeof(uint32_t); i++) top->BR_R_PAYLOAD[i] = record[i];
        }
#endif
    }

    int cycle() {
        inputs();
        if (!single_eval) {
            top->BR_CLK = 0;
            top->eval();
        }
        int cready = top->BR_I_READY, rvalid = top->BR_O_VALID, rpayload = top->BR_O_PAYLOAD;
#if BR_RECORDS
        bool rtaken = record_offered && top->BR_R_READY;
#endif
#ifdef BR_CLK_PREV
        if (single_eval) top->rootp->BR_CLK_PREV = 0;   // the clock was low: this eval is a rising edge
#endif
        edge();
        if (offer >= 0 && cready) offer = -1;
#if BR_RECORDS
        if (rtaken) record_offered = false;
#endif
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

// Commands as whole records from now on (a top built with BR_RECORDS, a quiet host): ``payload``
// and ``arg_bits`` per header kind (op * 4 + LOAD_POINTS count - 1: payload bytes, -1 for an
// opcode that goes as bytes; the record's argument bits), ``arg_offset`` the op's bits. Returns 0
// if the build has no record stream.
int br_records(void *handle, const int *payload, const int *arg_bits, int arg_offset) {
#if BR_RECORDS
    Harness *h = static_cast<Harness *>(handle);
    std::memcpy(h->payload, payload, sizeof h->payload);
    std::memcpy(h->arg_bits, arg_bits, sizeof h->arg_bits);
    h->arg_offset = arg_offset;
    h->records = true;
    h->bytes_only = false;
    return 1;
#else
    (void)handle; (void)payload; (void)arg_bits; (void)arg_offset;
    return 0;
#endif
}

// One eval a clock cycle instead of two (sim/native/__init__.py checks that the generated model
// allows it: no sampled output port is computed in the input phase, the clock is the only
// trigger). Returns 0 if this build cannot (a waveform build: it dumps the clock low too).
int br_single_eval(void *handle, int on) {
#if defined(BR_CLK_PREV) && !BR_TRACE
    static_cast<Harness *>(handle)->single_eval = on != 0;
    return 1;
#else
    (void)handle; (void)on;
    return 0;
#endif
}

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
    h->bytes_only = false;                  // the stream after a reset starts at a command
    h->incomplete = false;
    if (h->driven) {                        // the host's offer stands on the wire until the edge
        h->inputs();
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
    h->offer = -1;
    h->record_offered = false;
    h->top->BR_I_VALID = 0;
    h->top->BR_O_READY = 0;
#if BR_RECORDS
    h->top->BR_R_VALID = 0;
#endif
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
    else if (h->incomplete) h->next_record();   // the rest of the record the queue ended in
    size_t received = 0;
    uint64_t quiet = 0;
    int status;
    for (;;) {
        if (received >= want) { status = 0; break; }
        if (received == capacity) { status = 1; break; }
        if (h->starved() && quiet > patience) { status = 2; break; }
        bool offered = h->offer >= 0, recorded = h->record_offered;
        int byte = h->cycle();
        quiet = (offered && h->offer < 0) || (recorded && !h->record_offered) || byte >= 0 ? 0 : quiet + 1;
        if (byte >= 0) out[received++] = (uint8_t)byte;
        h->drive();
    }
    *got = received;
    return status;
}

}  // extern "C"
