"""A seeded generator of G-code programs, valid and slightly broken, for robustness tests.

``program(seed)`` builds one program from a small grammar: motion in every plane (UVW included) and
every way into an arc (G2/G3, G12/G13, canned cycles, cutter compensation, polar, G5.x, lathe G7x),
modal codes, G10/G52/G92 combinations, parameters and expressions that overflow or produce NaN
(``SQRT[-1]``, ``ASIN[2]``, ``[1/0]``, ``EXP[1000]``), o-word flow with bad labels, huge loop counts
and deep recursion, odd numbers (``1e400``, ``-0``, ``.``), unbalanced brackets and comments; then a
few lines are mutated (a word dropped, doubled, a value cut off). The same seed gives the same text.
"""

from __future__ import annotations

import random

PLANES = ["G17", "G18", "G19", "G17.1", "G18.1", "G19.1"]

GOOD_NUMBERS = ["0", "1", "-1", "2.5", "-0", "-0.0", ".5", "-.5", "10", "100", "0.0001", "360", "-360", "#1",
                "#<v>", "#<_g>", "[#1 + 2]", "[2 * #<v>]", "ABS[-2]", "[1 LT 2]", "SIN[30]", "[10 MOD 3]"]
NUMBERS = [
    *GOOD_NUMBERS, "1e400", "1e-400", ".", "-", "+", "", "9" * 40, "-" + "9" * 40, "0.", "00012", "#5220",
    "[1/0]", "[0/0]", "SQRT[-1]", "ASIN[2]", "ACOS[-2]", "EXP[1000]", "LN[0]", "LN[-1]", "[10**400]",
    "[0**-1]", "[-8**0.5]", "[1 MOD 0]", "[ATAN[0]/[0]]", "[EXP[800]*0]", "ROUND[EXP[1000]]",
    "FIX[-EXP[710]]", "[#1/#2]", "[1+]", "[[1]", "[1]]", "SIN[", "ABS[-2]", "EXISTS[#<v>]", "[2 EQ 2]",
    "[1 AND 0]", "[1 LT 2]", "[#<v> GT 1e3]", "##1", "#[1+1]", "#-1", "#99999", "#[0/0]",
]

AXES = "XYZABCUVW"
ARC_WORDS = "IJKR"


class _Rng(random.Random):
    bad: float = 0.1
    """How often a value is one of the odd ones (per program)."""


def _pick(r: random.Random, options: list[str], good: int) -> str:
    """One of ``options``; only the first ``good`` (the valid ones) in a program without odd values."""
    return r.choice(options if getattr(r, "bad", 0.1) else options[:good])


def _num(r: random.Random) -> str:
    x = r.random()
    if x < getattr(r, "bad", 0.1):
        return r.choice(NUMBERS)
    if x < 0.8:
        return f"{r.uniform(-50, 50):.3f}".rstrip("0").rstrip(".") or "0"
    return r.choice(GOOD_NUMBERS)


def _words(r: random.Random, letters: str, most: int = 3) -> str:
    return " ".join(f"{r.choice(letters)}{_num(r)}" for _ in range(r.randint(0, most)))


def _motion(r: random.Random) -> str:
    kind = r.randrange(12)
    if kind == 0:
        return f"G{r.choice(['0', '1'])} {_words(r, AXES)}"
    if kind == 1:
        return f"G{r.choice(['2', '3'])} {_words(r, 'XYZUVW')} {_words(r, ARC_WORDS, 2)} {_words(r, 'FP', 1)}"
    if kind == 2:
        return f"G{r.choice(['12', '13'])} {_words(r, 'IDF', 2)}"
    if kind == 3:
        cyc = r.choice(["G81", "G82", "G83", "G73", "G84", "G74", "G85", "G86", "G87", "G88", "G89", "G76"])
        return f"{r.choice(['G98', 'G99', ''])} {cyc} {_words(r, 'XYZUVWRQPLIJKEH', 5)}"
    if kind == 4:
        side = r.choice(["G41", "G42", "G41.1", "G42.1", "G40"])
        return f"{side} {_words(r, 'D', 1)} G{r.choice(['1', '2', '3'])} {_words(r, 'XYZ', 2)} " \
               f"{_words(r, 'IJR', 1)}"
    if kind == 5:
        return f"G16\nG{r.choice(['0', '1', '2', '3'])} @{_num(r)} ^{_num(r)} {_words(r, 'RIJZ', 1)}\nG15"
    if kind == 6:
        g5 = r.choice(["G5", "G5.1", "G5.2", "G5.3"])
        return f"{g5} {_words(r, 'XYZIJPQLRK', 4)}"
    if kind == 7:
        g7 = r.choice(["G70", "G71", "G72", "G71.1", "G72.2", "G7", "G8"])
        return f"{g7} {_words(r, 'QXZDIRKUW', 4)}"
    if kind == 8:
        return f"G{r.choice(['33', '33.1', '38.2', '38.3', '38.4', '38.5'])} {_words(r, 'XYZK', 2)}"
    if kind == 9:
        return f"G{r.choice(['28', '30', '28.1', '30.1', '53 G0', '53 G1'])} {_words(r, AXES, 2)}"
    if kind == 10:
        return f"G{r.choice(['68', '69', '51', '50', '22', '23'])} {_words(r, 'XYZRPIJ', 2)}"
    return f"G{r.choice(['80', '4'])} {_words(r, 'P', 1)}"


def _modal(r: random.Random) -> str:
    codes = [*PLANES, "G20", "G21", "G90", "G91", "G90.1", "G91.1", "G93", "G94", "G95", "G7", "G8",
             "G96 D1000 S50", "G97", "G61", "G61.1", "G64", "G64 P0.01 Q0.01", "G43", "G43 H1", "G43.1 Z1",
             "G43.2 H2", "G49", "G54", "G55", "G59.3", "G59.4", "M3 S1000", "M4 S10", "M5", "M7", "M8",
             "M9", "M48", "M49", "M50 P0", "M51 P1", "M52 P1", "M53 P1", "M19 R90", "T1 M6", "M61 Q2",
             "M62 P1", "M65 P0", "M66 P0 L0", "M66 P0 L3 Q1", "M67 E0 Q1", "M68 E1 Q2", "M70", "M71",
             "M72", "M73", "M101", "M150", "S-5", "F-1", "F0", "M0", "M1", "G4 P-1"]
    feed = " F" + _num(r) if r.random() < .3 else ""
    return " ".join(r.choice(codes) for _ in range(r.randint(1, 3))) + feed


def _offsets(r: random.Random) -> str:
    forms = [
        f"G10 L2 P{r.choice(['0', '1', '9', '10', '-1', '1.5', ''])} {_words(r, AXES + 'R', 3)}",
        f"G10 L20 P{r.choice(['1', '2', '10'])} {_words(r, AXES, 2)}",
        f"G10 L1 P{r.choice(['1', '0', '99999', '-2'])} {_words(r, 'XZRIJQ', 3)}",
        f"G10 L10 P1 {_words(r, 'XZR', 2)}", f"G10 L11 P2 {_words(r, 'XZ', 2)}",
        f"G10 L{r.choice(['3', '7', ''])} P1 X1", f"G52 {_words(r, AXES, 3)}",
        f"G92 {_words(r, AXES, 3)}", "G92.1", "G92.2", "G92.3", f"G52 G92 {_words(r, AXES, 2)}",
        f"G10 L2 P1 G92 {_words(r, 'XY', 2)}",
    ]
    return r.choice(forms)


def _params(r: random.Random) -> str:
    target = _pick(r, ["#1", "#2", "#<v>", "#<_g>", "#5221", "#[1+1]", "#31", "#5161", "#5220", "#5400",
                       "#-1", "#99999", "#<>", "#<v", "##1", "#[0/0]"], 8)
    op = _pick(r, ["+", "-", "*", "MOD", "AND", "OR", "XOR", "EQ", "GT", "/", "**"], 9)
    return f"{target} = [{_num(r)} {op} {_num(r)}]"


def _comment(r: random.Random) -> str:
    return _pick(r, ["(plain)", "(MSG, hello #1)", "(DEBUG, v=#<v> g=#<_g>)", "(PRINT, #1)", "; tail",
                     "(unclosed", "())", "((nested))", "(LOGOPEN,x.log)", "(LOGAPPEND,x)",
                     "(LOG,#1)", "(LOGCLOSE)", "(PROBEOPEN x)", "(ABORT, stop)", "(DEBUG,#<_ini[a]b>)"], 5)


def _oword(r: random.Random) -> list[str]:
    label = _pick(r, ["o100", "o<s>", "o<S>", "o<s s>", "o[1+1]", "o<>", "o<../up>", "o", "o-1", "o1.5",
                      "o<" + "x" * 80 + ">", "o#1", "o<missing>"], 5)
    other = r.choice(["o100", "o<s>", "o200", "o<t>"])
    count = _pick(r, ["2", "0", "-1", "#1", ".5", "1000000000", "1e400", "[1/0]", "SQRT[-1]"], 5)
    cond = _pick(r, ["[0]", "[#1 LT 3]", "[#<v>]", "[1]", "[SQRT[-1]]", "[1/0]", "", "[1 EQ 1"], 3)
    kind = r.randrange(9)
    if kind == 0:
        return [f"{label} sub", f"G1 X#1 F{_num(r)}", f"{r.choice([label, other])} endsub",
                f"{label} call [1] [2]"]
    if kind == 1:
        return [f"{label} repeat [{count}]", "#1 = [#1 + 1]", f"{r.choice([label, other])} endrepeat"]
    if kind == 2:
        return [f"{label} while {cond}", "#1 = [#1 + 1]", f"{label} {r.choice(['break', 'continue', ''])}",
                f"{r.choice([label, other])} endwhile"]
    if kind == 3:
        return [f"{label} do", "#1 = [#1 + 1]", f"{r.choice([label, other])} while {cond}"]
    if kind == 4:
        return [f"{label} if {cond}", "G0 X1", f"{label} elseif {cond}", f"{label} else",
                f"{r.choice([label, other])} endif"]
    if kind == 5:  # recursion, unbounded unless the call depth limit stops it
        return ["o<r> sub", f"o<r> call [{count}]", "o<r> endsub", "o<r> call [1]"]
    if kind == 6:
        return [f"{label} call {cond} {cond}", f"{label} return [{_num(r)}]"]
    if kind == 7:
        return [f"M98 P{r.choice(['100', '1', '0', '-5', '1.5', ''])} L{count}", "M99", "O100", "M99"]
    stray = ["endsub", "endwhile", "endif", "endrepeat", "break", "continue", "return", "else", "x"]
    return [f"{label} {r.choice(stray)}"]


def _mutate(r: random.Random, line: str) -> str:
    if not line:
        return line
    op = r.randrange(6)
    pos = r.randrange(len(line) + 1)
    if op == 0:
        return line[:pos] + line[pos + 1:]
    if op == 1:
        return line[:pos] + r.choice("[]()<>#=.-+GXIJRPLO;%/ \t\x00é") + line[pos:]
    if op == 2:
        return line + " " + line
    if op == 3:
        return line[:pos]
    if op == 4:
        return line[:pos] + r.choice(NUMBERS) + line[pos:]
    return line.replace("[", "", 1)


def program(seed: int, lines: int = 12, broken: bool = True) -> str:
    """A program of about ``lines`` lines (deterministic in ``seed``), ending with M2 most times;
    ``broken=False``: no odd values and no mutations (most such programs still have a mistake)."""
    r = _Rng(seed)
    r.bad = r.choice([0.0, 0.02, 0.05, 0.2]) if broken else 0.0
    mutate = r.choice([0.0, 0.02, 0.1]) if broken else 0.0
    out = [r.choice(["%", "", "G20", "G91", "G18", "G19"]), "G21 G90 G17 F300 #1 = 0 #<v> = 1 #<_g> = 2"]
    for _ in range(r.randint(1, lines)):
        kind = r.randrange(10)
        if kind <= 2:
            chunk = [_motion(r)]
        elif kind == 3:
            chunk = [r.choice(PLANES) + " " + _motion(r)]
        elif kind == 4:
            chunk = [_modal(r)]
        elif kind == 5:
            chunk = [_offsets(r)]
        elif kind == 6:
            chunk = [_params(r)]
        elif kind == 7:
            chunk = [_comment(r)]
        else:
            chunk = _oword(r)
        if r.random() < mutate:
            i = r.randrange(len(chunk))
            chunk[i] = _mutate(r, chunk[i])
        out.extend(chunk)
    out.append(r.choice(["M2", "M2", "M30", "%", "", "M2\nG0 X1"]))
    return "\n".join(out) + "\n"
