// Behavioural model of the one Lattice ECP5 MULT18X18D configuration blockray instantiates
// (blockray.rtl.processor._product with the ECP5 target; parameters MULT18X18D_PARAMS):
//
//   A, B registered on CLK0 (REG_INPUTA_CLK = REG_INPUTB_CLK = "CLK0"), their signed 18 x 18
//   product registered on CLK0 (REG_OUTPUT_CLK = "CLK0"), no pipeline register, no C register;
//   CE0 clock enable, RST0 synchronous reset of all three registers to 0 (RESETMODE = "SYNC").
//   Latency 2 cycles from A, B to P; P = A * B as a signed 36-bit value.
//
// For simulation only (Verilator, tests/test_dsp_ecp5.py), never for synthesis: Yosys and nextpnr
// use their own MULT18X18D. It models nothing else: any other parameter value stops the
// simulation at time 0 ($fatal), and so does, at a clock edge, SIGNEDA/SIGNEDB other than 1,
// SOURCEA/SOURCEB other than 0, C other than 0 or CE0 other than 1 (the values blockray ties).
// The parameter defaults are Lattice's (as in Yosys's cells_bb.v), so an instance that does not
// set a parameter is checked against the default, not waved through. Ports that blockray leaves
// unconnected (CLK1..3, CE1..3, RST1..3, SRIA, SRIB and every output but P) are not declared.
`default_nettype none
module MULT18X18D (
    input wire A0, A1, A2, A3, A4, A5, A6, A7, A8, A9, A10, A11, A12, A13, A14, A15, A16, A17,
    input wire B0, B1, B2, B3, B4, B5, B6, B7, B8, B9, B10, B11, B12, B13, B14, B15, B16, B17,
    input wire C0, C1, C2, C3, C4, C5, C6, C7, C8, C9, C10, C11, C12, C13, C14, C15, C16, C17,
    input wire SIGNEDA, SIGNEDB, SOURCEA, SOURCEB,
    input wire CLK0, CE0, RST0,
    output wire P0, P1, P2, P3, P4, P5, P6, P7, P8, P9, P10, P11, P12, P13, P14, P15, P16, P17, P18, P19, P20, P21, P22, P23, P24, P25, P26, P27, P28, P29, P30, P31, P32, P33, P34, P35
);
    parameter REG_INPUTA_CLK = "NONE";
    parameter REG_INPUTA_CE = "CE0";
    parameter REG_INPUTA_RST = "RST0";
    parameter REG_INPUTB_CLK = "NONE";
    parameter REG_INPUTB_CE = "CE0";
    parameter REG_INPUTB_RST = "RST0";
    parameter REG_INPUTC_CLK = "NONE";
    parameter REG_INPUTC_CE = "CE0";
    parameter REG_INPUTC_RST = "RST0";
    parameter REG_PIPELINE_CLK = "NONE";
    parameter REG_PIPELINE_CE = "CE0";
    parameter REG_PIPELINE_RST = "RST0";
    parameter REG_OUTPUT_CLK = "NONE";
    parameter REG_OUTPUT_CE = "CE0";
    parameter REG_OUTPUT_RST = "RST0";
    parameter CLK0_DIV = "ENABLED";
    parameter CLK1_DIV = "ENABLED";
    parameter CLK2_DIV = "ENABLED";
    parameter CLK3_DIV = "ENABLED";
    parameter HIGHSPEED_CLK = "NONE";
    parameter GSR = "ENABLED";
    parameter CAS_MATCH_REG = "FALSE";
    parameter SOURCEB_MODE = "B_SHIFT";
    parameter MULT_BYPASS = "DISABLED";
    parameter RESETMODE = "SYNC";

    wire signed [17:0] a = {A17, A16, A15, A14, A13, A12, A11, A10, A9, A8, A7, A6, A5, A4, A3, A2, A1, A0};
    wire signed [17:0] b = {B17, B16, B15, B14, B13, B12, B11, B10, B9, B8, B7, B6, B5, B4, B3, B2, B1, B0};
    wire [17:0] c = {C17, C16, C15, C14, C13, C12, C11, C10, C9, C8, C7, C6, C5, C4, C3, C2, C1, C0};
    reg signed [17:0] a_r = 18'sd0, b_r = 18'sd0;
    reg signed [35:0] p_r = 36'sd0;
    assign {P35, P34, P33, P32, P31, P30, P29, P28, P27, P26, P25, P24, P23, P22, P21, P20, P19, P18, P17, P16, P15, P14, P13, P12, P11, P10, P9, P8, P7, P6, P5, P4, P3, P2, P1, P0} = p_r;

    reg bad;
    initial begin
        bad = 0;
        if (REG_INPUTA_CLK != "CLK0") begin $display("MULT18X18D %m: REG_INPUTA_CLK = %s, the model supports only \"CLK0\"", REG_INPUTA_CLK); bad = 1; end
        if (REG_INPUTA_CE != "CE0") begin $display("MULT18X18D %m: REG_INPUTA_CE = %s, the model supports only \"CE0\"", REG_INPUTA_CE); bad = 1; end
        if (REG_INPUTA_RST != "RST0") begin $display("MULT18X18D %m: REG_INPUTA_RST = %s, the model supports only \"RST0\"", REG_INPUTA_RST); bad = 1; end
        if (REG_INPUTB_CLK != "CLK0") begin $display("MULT18X18D %m: REG_INPUTB_CLK = %s, the model supports only \"CLK0\"", REG_INPUTB_CLK); bad = 1; end
        if (REG_INPUTB_CE != "CE0") begin $display("MULT18X18D %m: REG_INPUTB_CE = %s, the model supports only \"CE0\"", REG_INPUTB_CE); bad = 1; end
        if (REG_INPUTB_RST != "RST0") begin $display("MULT18X18D %m: REG_INPUTB_RST = %s, the model supports only \"RST0\"", REG_INPUTB_RST); bad = 1; end
        if (REG_INPUTC_CLK != "NONE") begin $display("MULT18X18D %m: REG_INPUTC_CLK = %s, the model supports only \"NONE\"", REG_INPUTC_CLK); bad = 1; end
        if (REG_INPUTC_CE != "CE0") begin $display("MULT18X18D %m: REG_INPUTC_CE = %s, the model supports only \"CE0\"", REG_INPUTC_CE); bad = 1; end
        if (REG_INPUTC_RST != "RST0") begin $display("MULT18X18D %m: REG_INPUTC_RST = %s, the model supports only \"RST0\"", REG_INPUTC_RST); bad = 1; end
        if (REG_PIPELINE_CLK != "NONE") begin $display("MULT18X18D %m: REG_PIPELINE_CLK = %s, the model supports only \"NONE\"", REG_PIPELINE_CLK); bad = 1; end
        if (REG_PIPELINE_CE != "CE0") begin $display("MULT18X18D %m: REG_PIPELINE_CE = %s, the model supports only \"CE0\"", REG_PIPELINE_CE); bad = 1; end
        if (REG_PIPELINE_RST != "RST0") begin $display("MULT18X18D %m: REG_PIPELINE_RST = %s, the model supports only \"RST0\"", REG_PIPELINE_RST); bad = 1; end
        if (REG_OUTPUT_CLK != "CLK0") begin $display("MULT18X18D %m: REG_OUTPUT_CLK = %s, the model supports only \"CLK0\"", REG_OUTPUT_CLK); bad = 1; end
        if (REG_OUTPUT_CE != "CE0") begin $display("MULT18X18D %m: REG_OUTPUT_CE = %s, the model supports only \"CE0\"", REG_OUTPUT_CE); bad = 1; end
        if (REG_OUTPUT_RST != "RST0") begin $display("MULT18X18D %m: REG_OUTPUT_RST = %s, the model supports only \"RST0\"", REG_OUTPUT_RST); bad = 1; end
        if (CLK0_DIV != "ENABLED") begin $display("MULT18X18D %m: CLK0_DIV = %s, the model supports only \"ENABLED\"", CLK0_DIV); bad = 1; end
        if (CLK1_DIV != "ENABLED") begin $display("MULT18X18D %m: CLK1_DIV = %s, the model supports only \"ENABLED\"", CLK1_DIV); bad = 1; end
        if (CLK2_DIV != "ENABLED") begin $display("MULT18X18D %m: CLK2_DIV = %s, the model supports only \"ENABLED\"", CLK2_DIV); bad = 1; end
        if (CLK3_DIV != "ENABLED") begin $display("MULT18X18D %m: CLK3_DIV = %s, the model supports only \"ENABLED\"", CLK3_DIV); bad = 1; end
        if (HIGHSPEED_CLK != "NONE") begin $display("MULT18X18D %m: HIGHSPEED_CLK = %s, the model supports only \"NONE\"", HIGHSPEED_CLK); bad = 1; end
        if (GSR != "DISABLED") begin $display("MULT18X18D %m: GSR = %s, the model supports only \"DISABLED\"", GSR); bad = 1; end
        if (CAS_MATCH_REG != "FALSE") begin $display("MULT18X18D %m: CAS_MATCH_REG = %s, the model supports only \"FALSE\"", CAS_MATCH_REG); bad = 1; end
        if (SOURCEB_MODE != "B_SHIFT") begin $display("MULT18X18D %m: SOURCEB_MODE = %s, the model supports only \"B_SHIFT\"", SOURCEB_MODE); bad = 1; end
        if (MULT_BYPASS != "DISABLED") begin $display("MULT18X18D %m: MULT_BYPASS = %s, the model supports only \"DISABLED\"", MULT_BYPASS); bad = 1; end
        if (RESETMODE != "SYNC") begin $display("MULT18X18D %m: RESETMODE = %s, the model supports only \"SYNC\"", RESETMODE); bad = 1; end
        if (bad) $fatal(1, "MULT18X18D %m: unsupported configuration");
    end

    always @(posedge CLK0) begin
        if (SIGNEDA !== 1'b1 || SIGNEDB !== 1'b1 || SOURCEA !== 1'b0 || SOURCEB !== 1'b0 || c !== 18'd0 || CE0 !== 1'b1)
            $fatal(1, "MULT18X18D %m: SIGNEDA=%b SIGNEDB=%b SOURCEA=%b SOURCEB=%b C=%h CE0=%b: the model supports 1, 1, 0, 0, 0, 1",
                   SIGNEDA, SIGNEDB, SOURCEA, SOURCEB, c, CE0);
        if (RST0) begin
            a_r <= 18'sd0;
            b_r <= 18'sd0;
            p_r <= 36'sd0;
        end else begin
            a_r <= a;
            b_r <= b;
            p_r <= a_r * b_r;
        end
    end
endmodule
`default_nettype wire
