"""Seeded random G-code programs for the differential test against rs274 (no tests here).

Each program mixes what real programs do: straight moves and arcs in the three planes, absolute and
incremental distance, inch and millimetre, coordinate systems (G10 L2 / L20, rotation), G92, tool
length offsets, tool changes, G53 / G28 / G30, canned cycles, parameters and expressions, polar
coordinates, subroutines with M73. Arcs are built from a centre offset and an angle, so they are valid
wherever the tool is. The same seed gives the same programs.
"""

from __future__ import annotations

import math
import random
from pathlib import Path

from tests.rs274_oracle import Case

TOOL_TABLE = """T1 P1 Z10 D6 ;
T2 P2 Z25.5 D3 ;
T3 P3 Z-4 X0.5 D10 ;
T4 P4 Z0 D0 ;
"""


def _num(r: random.Random, lo: float, hi: float, digits: int = 3) -> str:
    return f"{r.uniform(lo, hi):.{digits}f}"


def _axes(r: random.Random, incremental: bool, letters: str = "XYZ") -> str:
    chosen = [a for a in letters if r.random() < 0.6] or [r.choice(letters)]
    span = 20.0 if incremental else 60.0
    return " ".join(f"{a}{_num(r, -span, span)}" for a in chosen)


def _arc(r: random.Random, plane: int, incremental: bool) -> str:
    first, second, ijk = {17: ("X", "Y", "IJ"), 18: ("Z", "X", "KI"), 19: ("Y", "Z", "JK")}[plane]
    i, j = r.uniform(-15, 15), r.uniform(-15, 15)
    if math.hypot(i, j) < 1.0:
        i += 2.0
    rad = math.hypot(i, j)
    theta = r.uniform(0, 2 * math.pi)
    d1, d2 = i + rad * math.cos(theta), j + rad * math.sin(theta)
    code = r.choice(("G2", "G3"))
    names = {"X": "_x", "Y": "_y", "Z": "_z"}
    if incremental:
        e1, e2 = f"{d1:.4f}", f"{d2:.4f}"
    else:
        e1 = f"[#<{names[first]}>+{d1:.4f}]"
        e2 = f"[#<{names[second]}>+{d2:.4f}]"
    turns = f" P{r.randint(2, 3)}" if r.random() < 0.1 else ""
    normal = ""
    if r.random() < 0.2:
        letter = {17: "Z", 18: "Y", 19: "X"}[plane]
        normal = f" {letter}{_num(r, -5, 5) if incremental else _num(r, -20, 20)}"
    if r.random() < 0.2 and not turns:
        # R format: the short or long way round to the same end point
        chord = math.hypot(d1, d2)
        if chord > 1e-3:
            radius = rad if r.random() < 0.5 else -rad
            return f"{code} {first}{e1} {second}{e2}{normal} R{radius:.6f}"
    return f"{code} {first}{e1} {second}{e2}{normal} {ijk[0]}{i:.4f} {ijk[1]}{j:.4f}{turns}"


def program(seed: int, lines: int = 30, avoid_known: bool = True) -> str:
    """One program. ``avoid_known`` leaves out the construct docs/interpreter.md lists as a known
    difference: G10 L2 R while a G92/G52 offset may be active (LinuxCNC loses the current point, canon
    does not)."""
    r = random.Random(seed)
    g92 = False
    out = ["G21 G17 G90 G40 G49 G80 G94 F500", "#5161=10 #5162=20 #5163=30 #5181=-5 #5182=5 #5183=15"]
    plane, incremental, tool_loaded, subs = 17, False, False, []
    # LinuxCNC keeps a tool length offset in the units it was applied in: a G20/G21 change while one
    # is active, then G49 or G43, moves the tool by the unit difference (docs/interpreter.md). The
    # generator changes units only with no tool length offset active, and not inside subroutines.
    tlo = False
    for _ in range(lines):
        pick = r.random()
        if pick < 0.25:
            out.append(f"G{r.choice((0, 1))} {_axes(r, incremental)}")
        elif pick < 0.37:
            out.append(_arc(r, plane, incremental))
        elif pick < 0.41:
            plane = r.choice((17, 18, 19))
            out.append(f"G{plane}")
        elif pick < 0.45:
            incremental = not incremental
            out.append("G91" if incremental else "G90")
        elif pick < 0.48:
            out.append(r.choice(("G20", "G21")) if not tlo else "G4 P0")
        elif pick < 0.53:
            rot = f" R{_num(r, -40, 40, 1)}" if r.random() < 0.3 and not (avoid_known and g92) else ""
            out.append(f"G10 L2 P{r.randint(1, 3)} {_axes(r, False)}{rot}")
        elif pick < 0.55:
            out.append(f"G10 L20 P{r.randint(0, 3)} {_axes(r, False)}")
        elif pick < 0.59:
            out.append(r.choice(("G54", "G55", "G56")))
        elif pick < 0.62:
            code = r.choice((f"G92 {_axes(r, False)}", "G92.1", "G92.2", "G92.3"))
            g92 = (g92 or code.startswith("G92 ")) and code != "G92.1"
            out.append(code)
        elif pick < 0.64:
            code = r.choice((f"G52 {_axes(r, False)}", "G52 X0 Y0 Z0"))
            g92 = g92 or code != "G52 X0 Y0 Z0"
            out.append(code)
        elif pick < 0.68:
            n = r.randint(1, 4)
            if r.random() < 0.6:
                out.append(f"T{n} M6 G43")
                tlo = True
            else:
                out.append(f"T{n} M6")
            tool_loaded = True
        elif pick < 0.70:
            code = r.choice(("G49", f"G43.1 Z{_num(r, -10, 10)}", "G43" if tool_loaded else "G49",
                             f"G43 H{r.randint(1, 4)}"))
            out.append(code)
            tlo = code != "G49"
        elif pick < 0.73:
            out.append(r.choice((f"G53 G0 Z{_num(r, -5, 5)}", f"G53 G1 X{_num(r, -30, 30)} Y1",
                                 "G28", f"G28 Z{_num(r, -5, 5)}", "G30", "G30 X1", "G28.1")))
        elif pick < 0.79:
            if incremental:
                out.append("G90")
                incremental = False
            code = r.choice((81, 82, 83, 73, 85, 89, 86))
            extra = {82: " P0.5", 83: " Q2", 73: " Q1.5", 89: " P0.2", 86: " P0.1"}.get(code, "")
            spindle = "M3 S1000 " if code == 86 else ""
            letters = {17: "XY", 18: "XZ", 19: "YZ"}[plane]
            normal = {17: "Z", 18: "Y", 19: "X"}[plane]
            pos = " ".join(f"{a}{_num(r, -30, 30)}" for a in letters)
            out.append(f"{spindle}G{r.choice((98, 99))} G{code} {pos} {normal}{_num(r, -10, -1)} R2{extra}")
            if r.random() < 0.5:
                pos = " ".join(f"{a}{_num(r, -30, 30)}" for a in letters if r.random() < 0.7) or "X1"
                out.append(pos)
            out.append("G80")
        elif pick < 0.85:
            k = r.randint(1, 5)
            expr = r.choice((f"[{_num(r, -9, 9)} * 2 + #{k}]", f"[SIN[{_num(r, 0, 90)}] * 10]",
                             f"[{_num(r, 0, 2)} LT 1.00001]", f"[{_num(r, 0.99999, 1.00001, 6)} GE 1]",
                             f"[{r.choice(('1', '1.0000', '0.998', '1.002'))} EQ 1]",
                             f"[ABS[{_num(r, -5, 5)}] MOD 3]",
                             f"[FIX[{_num(r, -5, 5)}] + FUP[{_num(r, -5, 5)}]]"))
            out.append(f"#{k} = {expr}")
            out.append(f"G1 X[#{k} * 3] Y[#{(k % 5) + 1}]")
        elif pick < 0.89 and plane == 17:
            if r.random() < 0.5:
                out.append(f"G0 @{_num(r, 1, 40)} ^{_num(r, -180, 180)}")
            else:
                out.append(f"G1 ^{_num(r, -90, 90)}")
        elif pick < 0.93:
            name = f"s{len(subs)}"
            subs.append(name)
            body = r.choice(("G91\nG1 X1 Y-1\n", "G18\nG90\n", "G55\nG1 Z-1\n",
                             "G0 X1\n" if tlo else "G20\nG0 X1\n"))
            out.append(f"o<{name}> sub\nM73\n{body}o<{name}> endsub\no<{name}> call\nG1 X2 Y3 Z1")
        else:
            out.append(r.choice(("M3 S1200", "M5", "M8", "M9", "G4 P0.1", "G61", "G64 P0.05", "M1")))
    out.append("M2")
    return "\n".join(out) + "\n"


def cases(n: int, seed: int, tmp: Path, avoid_known: bool = True) -> list[Case]:
    """``n`` programs from seeds ``seed`` .. ``seed + n - 1``, each in its own directory under tmp."""
    root = tmp / f"canon-random-{seed}-{n}-{int(avoid_known)}"
    out = []
    for k in range(seed, seed + n):
        d = root / f"p{k:05d}"
        d.mkdir(parents=True, exist_ok=True)
        (d / "test.ngc").write_text(program(k, avoid_known=avoid_known))
        (d / "tools.tbl").write_text(TOOL_TABLE)
        out.append(Case(f"random/{k}", d, "test.ngc", tool_table="tools.tbl", subroutine_path=["."]))
    return out
