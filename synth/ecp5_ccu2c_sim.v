// Behavioural model of the Lattice ECP5 CCU2C carry cell as blockray instantiates it
// (blockray.rtl.lutdot, the filtered and lean cells' products with ECP5Target(fabric_units={"cell"})):
// two halves, each a LUT4 over {D, C, B, A} (INITn) giving the propagate Pn, sum Sn = Pn ^ carry in,
// carry out = Pn ? carry in : Gn, where the generate Gn is the LUT4's entry at C = D = 0 (the LUT2
// over {B, A} of INITn[3:0]). INJECT1_0 = INJECT1_1 = "NO" only. The same semantics as Yosys's
// techlibs/ecp5/ccu2c_sim.vh (which nextpnr and ABC9 use) with INJECT1 "NO".
//
// For simulation only (Verilator, tests/test_lean.py), never for synthesis: any other INJECT1
// value stops the simulation at time 0 ($fatal).
`default_nettype none
module CCU2C (
    input wire CIN,
    input wire A0, B0, C0, D0, A1, B1, C1, D1,
    output wire S0, S1, COUT
);
    parameter [15:0] INIT0 = 16'h0000;
    parameter [15:0] INIT1 = 16'h0000;
    parameter INJECT1_0 = "YES";
    parameter INJECT1_1 = "YES";

    initial begin
        if (INJECT1_0 != "NO" || INJECT1_1 != "NO") $fatal(1, "CCU2C model: INJECT1_0/1 must be \"NO\"");
    end

    wire p0 = INIT0[{D0, C0, B0, A0}];
    wire g0 = INIT0[{2'b00, B0, A0}];
    wire c1 = p0 ? CIN : g0;
    wire p1 = INIT1[{D1, C1, B1, A1}];
    wire g1 = INIT1[{2'b00, B1, A1}];
    assign S0 = p0 ^ CIN;
    assign S1 = p1 ^ c1;
    assign COUT = p1 ? c1 : g1;
endmodule
`default_nettype wire
