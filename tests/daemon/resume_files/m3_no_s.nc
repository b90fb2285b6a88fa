(the operator set the spindle speed before the job: M3 carries no S)
G21 G90 G54
G0 Z5
G0 X3 Y3
M3
G1 Z-1 F200
G1 X18 F1000
G1 Y12
G1 X3
G1 Y3
G0 Z5
M5
M30
