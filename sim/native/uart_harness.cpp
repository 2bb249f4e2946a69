// The native UART harness: a Verilated top at its serial pins (rx, tx), clocked in C++.
//
// Built like harness.cpp (sim/native/__init__.py, build_native with harness="uart_harness.cpp")
// for --board ulx3s-sim: blockray.rtl.link.SerialLink around the board core. It plays the
// USB-serial bridge of sim/uart_cocotb.py, cycle for cycle, so both routes run the same clock
// cycles: queued bytes go out on rx as 8N1 frames of ``divisor`` cycles per bit, frames on tx are
// sampled in the middle of each bit, and a run ends after its cycles or on the clock cycle a frame
// delimiter (a zero byte) was decoded on tx. Ports by macro: BR_TOP, BR_CLK, BR_RST, BR_RX, BR_TX.
#include <cstddef>
#include <cstdint>
#include <vector>

#include "native_config.h"           // the BR_ macros, written by sim/native/__init__.py
#include "verilated.h"
#include BR_HEADER

namespace {

struct Uart {
    VerilatedContext context;
    BR_TOP *top = new BR_TOP(&context);
    uint32_t divisor;
    uint64_t cycles = 0;             // rising edges since the bridge started (after the reset)
    bool brk = false;
    // the driver: bytes queued for rx, the byte on the wire and its bit
    std::vector<uint8_t> queue;
    size_t head = 0;
    int bits[10];
    int bit = -1;                    // index in bits of the bit on rx, -1: idle
    uint32_t bit_left = 0;           // rising edges until the next bit
    // the monitor: waiting for a falling edge of tx, or the edges to the next sample
    int last_tx = 1;
    int sample = -1;                 // -1: waiting; 0: start bit's middle; 1..8: data; 9: stop
    uint32_t sample_left = 0;
    int byte = 0;
    std::vector<uint8_t> received;
    bool delimiter = false;

    ~Uart() { top->final(); delete top; }

    void edge() {
        top->BR_CLK = 0;
        top->eval();
        top->BR_CLK = 1;
        top->eval();
    }

    // what the driver coroutine does at a rising edge it waited for (and at the start)
    void next_byte() {
        bit = -1;
        if (brk || head == queue.size()) return;
        int b = queue[head++];
        bits[0] = 0;
        for (int k = 0; k < 8; k++) bits[1 + k] = (b >> k) & 1;
        bits[9] = 1;
        bit = 0;
        top->BR_RX = 0;
        bit_left = divisor;
    }

    void drive_edge() {
        if (bit < 0) { next_byte(); return; }
        if (--bit_left) return;
        if (brk || bit == 9) { next_byte(); return; }   // a break cuts the byte short
        top->BR_RX = bits[++bit];
        bit_left = divisor;
    }

    void monitor_edge() {
        int tx = top->BR_TX;
        if (sample < 0) {
            if (last_tx && !tx) { sample = 0; sample_left = divisor / 2; byte = 0; }
            last_tx = tx;
            if (sample < 0 || sample_left) return;
        } else if (--sample_left) {
            return;
        }
        // the edge a sample was waited for: tx as it is after it
        if (sample >= 1 && sample <= 8) byte |= tx << (sample - 1);
        if (sample == 9) {
            if (tx) {
                received.push_back((uint8_t)byte);
                if (byte == 0) delimiter = true;
            }
            sample = -1;
            last_tx = tx;
            return;
        }
        sample++;
        sample_left = divisor;
    }

    // one rising edge, then the bridge's reactions to it (the monitor first sees tx as the edge
    // left it; the driver sets rx for the next edge)
    void cycle() {
        edge();
        cycles++;
        monitor_edge();
        drive_edge();
    }
};

}  // namespace

extern "C" {

// The top held in reset for two rising edges with rx high, then one more edge: sim/uart_cocotb.py.
void *bu_open(uint32_t divisor) {
    Uart *u = new Uart();
    u->divisor = divisor;
    u->top->BR_RX = 1;
    u->top->BR_RST = 1;
    u->edge();
    u->edge();
    u->top->BR_RST = 0;
    u->edge();
    u->last_tx = u->top->BR_TX;
    return u;
}

void bu_close(void *handle) { delete static_cast<Uart *>(handle); }

void bu_write(void *handle, const uint8_t *data, size_t count) {
    Uart *u = static_cast<Uart *>(handle);
    if (u->head == u->queue.size()) { u->queue.clear(); u->head = 0; }
    u->queue.insert(u->queue.end(), data, data + count);
    if (u->bit < 0) u->next_byte();  // the driver was waiting for bytes: it starts at once
}

// A break: rx held low and the queue dropped (on), or rx high again (off).
void bu_break(void *handle, int on) {
    Uart *u = static_cast<Uart *>(handle);
    u->brk = on != 0;
    if (on) {
        u->queue.clear();
        u->head = 0;
        u->top->BR_RX = 0;
    } else {
        u->top->BR_RX = 1;
        if (u->bit < 0) u->next_byte();
    }
}

// Run at most ``cycles`` rising edges, less if a frame delimiter is decoded on tx (at once if one
// was decoded before). ``*ran``: the edges run; ``*queued``: bytes not yet sent on rx; the bytes
// decoded go to ``out`` (at most ``capacity``; ``*got`` of them), the rest stay for the next run.
void bu_run(void *handle, uint64_t cycles, uint8_t *out, size_t capacity, size_t *got, uint64_t *ran,
            size_t *queued) {
    Uart *u = static_cast<Uart *>(handle);
    uint64_t start = u->cycles;
    if (!u->delimiter) {
        while (u->cycles - start < cycles && !u->delimiter) u->cycle();
    }
    u->delimiter = false;
    size_t n = u->received.size() < capacity ? u->received.size() : capacity;
    for (size_t i = 0; i < n; i++) out[i] = u->received[i];
    u->received.erase(u->received.begin(), u->received.begin() + n);
    *got = n;
    *ran = u->cycles - start;
    *queued = u->queue.size() - u->head;
}

}  // extern "C"
