"""The geometry of LinuxCNC's lathe cycles G70, G71 and G72 (interp_g7x.cc), in the XZ plane.

Points are complex numbers ``z + x*1j`` in program units, as LinuxCNC computes them (its tolerances
are in program units too). A profile is a list of segments (lines, arcs, and the corner finishes A
(fillet) and C (chamfer) that become arcs and lines); the cycles turn it so that X and Z decrease
along it, offset it by the finishing allowance, and cut it: G70 along the profile in passes, G71/G72
in layers of depth I with escapes of R, pockets included (G71/G72), left out (G7x.1) or only them
(G7x.2). The moves go to an :class:`Output` (straight, rapid, arc). The algorithm, its order of
operations and its tolerances are LinuxCNC's, so the moves are.
"""

from __future__ import annotations

import copy
import math
from typing import ClassVar, Protocol

from gcode_canon.errors import GCodeError

TOL = 1e-6
_MAX_STEPS = 200_000  # bounds every loop LinuxCNC leaves unbounded (no input hangs)


class ProfileError(GCodeError):
    """A profile LinuxCNC's cycle refuses ("G7X error: ...")."""


def _c_str(p: complex) -> str:
    return f"({p.real:g},{p.imag:g})"  # as C++ prints a std::complex


class Output(Protocol):
    def straight(self, end: complex) -> None: ...
    def rapid(self, end: complex) -> None: ...
    def rapid_uncompensated(self, end: complex) -> None: ...
    def arc(self, ccw: bool, centre: complex, end: complex) -> None: ...


class Loc:
    """The tool's position while a cycle cuts (LinuxCNC passes it by reference)."""

    __slots__ = ("p",)

    def __init__(self, p: complex) -> None:
        self.p = p


class Segment:
    finish = 0.0

    def __init__(self, start: complex, end: complex) -> None:
        self.s, self.e = start, end

    def dup(self) -> Segment:
        return copy.copy(self)

    def monotonic(self) -> bool:
        return (self.e - self.s).real <= 1e-3

    def do_finish(self, prev: Segment, nxt: Segment) -> None:
        pass

    def flip_imag(self) -> None:
        self.s, self.e = self.s.conjugate(), self.e.conjugate()

    def flip_real(self) -> None:
        self.s, self.e = -self.s.conjugate(), -self.e.conjugate()

    def rotate(self) -> None:
        self.s, self.e = -self.s * 1j, -self.e * 1j

    def move(self, d: complex) -> None:
        self.s += d
        self.e += d

    def corner_finish(self, prev: Segment, nxt: Segment) -> complex:
        """Fit the corner finish between prev and nxt (their end and start move to its ends)."""
        p, n = prev.dup(), nxt.dup()
        p.offset(self.finish)
        n.offset(self.finish)
        if (p.e - n.s).real > 1e-2:
            self.finish = -self.finish
            p, n = prev.dup(), nxt.dup()
            p.offset(self.finish)
            n.offset(self.finish)
        if (p.e - n.s).real > 1e-2:
            raise ProfileError(f"Corner finish failed at {_c_str(prev.e)}")
        intersect(p, n)
        centre = (p.e + n.s) / 2.0
        p.offset(-self.finish)
        n.offset(-self.finish)
        self.s = prev.e = p.e
        self.e = nxt.s = n.s
        return centre

    # overridden
    def offset(self, d: float) -> None: raise NotImplementedError
    def radius(self) -> float: raise NotImplementedError
    def intersection_z(self, x: float, out: list[float]) -> None: raise NotImplementedError
    def draw(self, out: Output) -> None: raise NotImplementedError
    def climb(self, loc: Loc, out: Output) -> bool: raise NotImplementedError
    def climb_only(self, loc: Loc, out: Output) -> None: raise NotImplementedError
    def dive(self, loc: Loc, x: float, out: Output, fast: bool) -> bool: raise NotImplementedError


class Line(Segment):
    def offset(self, d: float) -> None:
        v = 1j * d * (self.s - self.e) / abs(self.s - self.e)
        self.s += v
        self.e += v

    def radius(self) -> float:
        return abs(self.s - self.e)

    def draw(self, out: Output) -> None:
        out.straight(self.e)

    def intersection_z(self, x: float, out: list[float]) -> None:
        s, e = self.s, self.e
        if min(s.imag, e.imag) > x + TOL or max(s.imag, e.imag) < x - TOL:
            return
        if abs((s - e).imag) < TOL:
            out.append(s.real)
            out.append(e.real)
        else:
            out.append((x - s.imag) / (e.imag - s.imag) * (e.real - s.real) + s.real)

    def climb(self, loc: Loc, out: Output) -> bool:
        if self.e.imag + TOL < self.s.imag:
            return True  # not climbing
        if abs(loc.p - self.s) > TOL:
            raise ProfileError("How did we get here?")
        out.straight(self.e)
        loc.p = self.e
        return False

    def climb_only(self, loc: Loc, out: Output) -> None:
        if self.e.imag < self.s.imag:
            return
        hits: list[float] = []
        self.intersection_z(loc.p.imag, hits)
        if not hits:
            return
        loc.p = complex(hits[0], loc.p.imag)
        out.straight(loc.p)
        out.straight(self.e)
        loc.p = self.e

    def dive(self, loc: Loc, x: float, out: Output, fast: bool) -> bool:
        if self.s.imag <= self.e.imag + TOL:
            return True  # not diving
        move = out.rapid if fast else out.straight
        if x < self.e.imag:
            move(self.e)
            loc.p = self.e
            return False
        hits: list[float] = []
        self.intersection_z(x, hits)
        if not hits:
            raise ProfileError("x too large in straight dive")
        loc.p = complex(hits[0], x)
        move(loc.p)
        return False


class Arc(Segment):
    def __init__(self, ccw: bool, start: complex, centre: complex, end: complex) -> None:
        super().__init__(start, end)
        self.ccw, self.c = ccw, centre

    def offset(self, d: float) -> None:
        r = abs(self.s - self.c)
        factor = (r + (1 if self.ccw else -1) * d) / r
        self.s = factor * (self.s - self.c) + self.c
        self.e = factor * (self.e - self.c) + self.c

    def radius(self) -> float:
        return min(abs(self.s - self.e), abs(self.s - self.c))

    def draw(self, out: Output) -> None:
        out.arc(self.ccw, self.c, self.e)

    def flip_imag(self) -> None:
        super().flip_imag()
        self.ccw = not self.ccw
        self.c = self.c.conjugate()

    def flip_real(self) -> None:
        super().flip_real()
        self.ccw = not self.ccw
        self.c = -self.c.conjugate()

    def rotate(self) -> None:
        super().rotate()
        self.c = -self.c * 1j

    def move(self, d: complex) -> None:
        super().move(d)
        self.c += d

    def monotonic(self) -> bool:
        if self.finish != 0:
            return True
        entry, exit_ = (self.s - self.c).imag, (self.e - self.c).imag
        dz = (self.e - self.s).real
        if self.ccw:
            return entry >= -1e-3 and exit_ >= -1e-3 and dz <= -1e-3
        return entry <= 1e-3 and exit_ <= 1e-3 and dz <= -1e-3

    def _on(self, p: complex) -> bool:
        a = ((self.s - self.c).conjugate() * (p - self.c)).imag
        b = ((self.e - self.c).conjugate() * (p - self.c)).imag
        return (a >= -TOL and b <= TOL) if self.ccw else (a <= TOL and b >= -TOL)

    def intersection_z(self, x: float, out: list[float]) -> None:
        r = abs(self.s - self.c)
        c = self.c
        q = -(x - r - c.imag) * (x + r - c.imag)
        if q < -TOL:
            return
        q = math.sqrt(max(q, 0.0))
        for p in (complex(c.real + q, x), complex(c.real - q, x)):
            if self._on(p):
                out.append(p.real)

    def _top(self) -> complex:
        """Where a climbing G3 leaves the arc: its end, or its top when it goes past it."""
        if self.e.real < self.c.real:
            return complex(self.c.real, self.c.imag + abs(self.s - self.c))
        return self.e

    def climb(self, loc: Loc, out: Output) -> bool:
        if not self.ccw:  # G2
            if loc.p.real > self.c.real:
                return True
            if abs(loc.p - self.e) > 1e-3:
                out.arc(self.ccw, self.c, self.e)
            loc.p = self.e
            return False
        if loc.p.real < self.c.real:
            return True
        ep = self._top()
        if abs(loc.p - ep) > 1e-3:
            out.arc(self.ccw, self.c, ep)
        loc.p = ep
        return True

    def dive(self, loc: Loc, x: float, out: Output, fast: bool) -> bool:
        if abs(loc.p - self.e) < TOL or (loc.p - self.e).real <= TOL:
            loc.p = self.e
            return False
        hits: list[float] = []
        self.intersection_z(x, hits)
        if not hits:
            self.intersection_z(x - TOL, hits)
        if self.ccw:  # G3
            if loc.p.real - TOL > self.c.real:
                return True
            if not hits or hits[-1] > self.c.real:
                out.arc(self.ccw, self.c, self.e)
                loc.p = self.e
            else:
                loc.p = complex(hits[-1], x)
                out.arc(self.ccw, self.c, loc.p)
            return False
        if loc.p.real <= self.c.real:
            return True  # already climbing
        if not hits:
            out.arc(self.ccw, self.c, self.e)
            loc.p = self.e
        elif hits[0] < self.c.real:
            pass  # hit at the back only: the pocket steps down
        else:
            loc.p = complex(hits[0], x)
            out.arc(self.ccw, self.c, loc.p)
        return False

    def climb_only(self, loc: Loc, out: Output) -> None:
        hits: list[float] = []
        self.intersection_z(loc.p.imag, hits)
        if not hits:
            return
        if not self.ccw:
            if hits[-1] > self.c.real:
                return
            loc.p = complex(hits[-1], loc.p.imag)
            out.straight(loc.p)
            if abs(loc.p - self.e) > 1e-3:
                out.arc(self.ccw, self.c, self.e)
            loc.p = self.e
            return
        if hits[0] < self.c.real:
            return
        loc.p = complex(hits[0], loc.p.imag)
        out.straight(loc.p)
        ep = self._top()
        if abs(loc.p - ep) > 1e-3:
            out.arc(self.ccw, self.c, ep)
        loc.p = ep


class Fillet(Arc):
    def __init__(self, size: float, at: complex) -> None:
        super().__init__(False, at, at, at)
        self.finish = size

    def do_finish(self, prev: Segment, nxt: Segment) -> None:
        self.c = self.corner_finish(prev, nxt)
        self.ccw = (self.s - self.c).imag > 0 or (self.e - self.c).imag > 0
        self.finish = 0.0


class Chamfer(Line):
    def __init__(self, size: float, at: complex) -> None:
        super().__init__(at, at)
        self.finish = size

    def do_finish(self, prev: Segment, nxt: Segment) -> None:
        self.corner_finish(prev, nxt)


def _norm(z: complex) -> float:
    return z.real * z.real + z.imag * z.imag


def intersect(a: Segment, b: Segment) -> None:
    """Move a's end and b's start to where the two meet (LinuxCNC's ``intersect_end`` family)."""
    if isinstance(b, Arc) and isinstance(a, Arc):
        ra, rb = abs(b.s - b.c), abs(a.s - a.c)
        d = abs(b.c - a.c)
        cos_b = (d * d + ra * ra - rb * rb) / 2.0 / ra / d
        rot = complex(cos_b, math.sqrt(1 - min(cos_b * cos_b, 1.0)))
        a.e = b.s = rot * (a.c - b.c) / d * ra + b.c
        return
    if isinstance(b, Arc) or isinstance(a, Arc):
        if abs(b.s - a.e) < TOL:
            return
        line, arc = (a, b) if isinstance(b, Arc) else (b, a)
        rot = (line.s - line.e).conjugate() / abs(line.s - line.e)
        pe = (arc.e - line.e) * rot
        pc = (arc.c - line.e) * rot  # type: ignore[attr-defined]
        q = _norm(pc - pe) - pc.imag * pc.imag
        q = math.sqrt(q) if q >= 0 else 0.0
        s1, s2 = (pc.real + q) / rot + line.e, (pc.real - q) / rot + line.e
        a.e = b.s = s1 if abs(b.s - s1) < abs(b.s - s2) else s2
        return
    rot = (b.s - b.e).conjugate() / abs(b.s - b.e)
    ps, pe = (a.s - b.e) * rot, (a.e - b.e) * rot
    if (ps - pe).imag == 0:
        raise ProfileError("Cannot intersect parallel lines")
    f = ps.imag / (ps - pe).imag
    a.e = b.s = (ps + f * (pe - ps)) / rot + b.e


class Swapped:
    """The moves of a turned profile, turned back (LinuxCNC's ``swapped_motion``)."""

    _MAP: ClassVar[dict] = {
        0: (lambda p: p, False), 1: (lambda p: -p.conjugate(), True), 2: (lambda p: p.conjugate(), True),
        3: (lambda p: -p, False), 4: (lambda p: 1j * p, False), 5: (lambda p: (1j * p).conjugate(), True),
        6: (lambda p: -(1j * p).conjugate(), True), 7: (lambda p: -1j * p, False)}

    def __init__(self, state: int, out: Output) -> None:
        self.f, self.flip = self._MAP[state]
        self.out = out

    def straight(self, end: complex) -> None:
        self.out.straight(self.f(end))

    def rapid(self, end: complex) -> None:
        self.out.rapid(self.f(end))

    def rapid_uncompensated(self, end: complex) -> None:
        self.out.rapid_uncompensated(self.f(end))

    def arc(self, ccw: bool, centre: complex, end: complex) -> None:
        self.out.arc(ccw != self.flip, self.f(centre), self.f(end))


class Profile:
    """A G7x profile and its cycles (LinuxCNC's ``g7x`` class)."""

    def __init__(self, segments: list[Segment] | None = None) -> None:
        self.segs: list[Segment] = segments if segments is not None else []
        self.delta = 0.5
        self.escape = 0.3 + 0.3j
        self.flip_state = 0
        self.pocket_starts: list[complex] = []
        self._steps = 0

    def copy(self) -> Profile:
        other = Profile([s.dup() for s in self.segs])
        other.delta, other.escape, other.flip_state = self.delta, self.escape, self.flip_state
        return other

    def _step(self) -> None:
        self._steps += 1
        if self._steps > _MAX_STEPS:
            raise ProfileError("the cycle does not converge on this profile")

    def rotate(self) -> None:
        for s in self.segs:
            s.rotate()
        self.flip_state ^= 4

    def swap(self) -> None:
        """Turn the profile so that X and Z decrease along it."""
        d = self.segs[0].e - self.segs[-1].e
        if d.imag > 0:
            for s in self.segs:
                s.flip_imag()
            self.flip_state ^= 2
        if d.real < 0:
            for s in self.segs:
                s.flip_real()
            self.flip_state ^= 1

    def monotonic(self) -> None:
        first = self.segs[0]
        if (first.e - first.s).real > 0:
            first.s = complex(first.e.real, first.s.imag)
        for s in self.segs:
            if not s.monotonic():
                raise ProfileError("Not monotonic")

    def do_finish(self) -> None:
        segs = self.segs
        for k in range(1, len(segs) - 1):
            segs[k].do_finish(segs[k - 1], segs[k + 1])
        self.segs = [s for s in segs if s.radius() >= 1e-3]

    def should_rotate(self) -> bool:
        paths = self.copy()
        paths.segs.pop(0)
        paths.swap()
        return any(not s.monotonic() for s in paths.segs)

    def g70(self, out: Output, x: float, z: float, d: float, e: float, passes: int) -> None:
        self.segs[0].s = complex(z, x)
        if self.should_rotate():
            self.rotate()
        self.swap()
        self.do_finish()
        self.monotonic()
        sw = Swapped(self.flip_state, out)
        for n in range(passes, 0, -1):
            distance = (n - 1) * (d - e) / passes + e
            paths = self.copy()
            paths.add_distance(distance)
            sw.rapid_uncompensated(paths.segs[0].s)  # LinuxCNC: with cutter compensation switched off
            sw.rapid(paths.segs[0].e)
            for s in paths.segs[1:]:
                s.draw(sw)

    def g71(self, out: Output, cycle: int, x: float, z: float, u: float, w: float, d: float, i: float,
            r: float, rotate: bool = False) -> None:
        """G71 (G72: ``rotate``); ``cycle`` 0 all, 1 without pockets, 2 only pockets."""
        self.segs[0].s = complex(z, x)
        if rotate:
            self.rotate()
        self.swap()
        self.do_finish()
        self.monotonic()
        self.add_distance(d)
        for s in self.segs:
            s.move(complex(w, u))
        sw = Swapped(self.flip_state, out)
        self.delta = max(i, 2 * TOL)
        self.escape = r * (1 + 1j)
        front = self.segs[0].s
        sw.rapid(front)
        last = self.segs[-1].e
        if last.imag < front.imag:
            self.segs.append(Line(last, complex(last.real, front.imag)))
        self.pocket_starts.append(front)
        self.pocket(cycle, front, 0, sw)

    def pocket(self, cycle: int, location: complex, p: int, out: Output) -> None:
        segs = self.segs
        n = len(segs)
        x = self.pocket_starts[-1].imag
        loc = Loc(location)
        if cycle == 2:  # skip the first roughing pass
            while p < n and not segs[p].dive(loc, -1e9, out, p == 0):
                p += 1
            cycle = 3
        while p < n:
            self._step()
            layers = 0
            while x - TOL > loc.p.imag:
                x -= self.delta
                layers += 1
                if layers > 10 * _MAX_STEPS:
                    raise ProfileError("the cycle does not converge on this profile")
            if segs[p].dive(loc, x, out, p == 0):
                if cycle == 1:  # no pockets: along the final contour to the end
                    for s in segs[p:]:
                        s.climb_only(loc, out)
                    return
                while p < n:
                    if segs[p].climb(loc, out):
                        if cycle == 3:
                            starts = self.pocket_starts
                            if loc.p.imag > starts[-1].imag and len(starts) > 1:
                                starts.pop()
                            if len(starts) == 1:
                                starts.append(loc.p)
                        self.pocket(cycle, loc.p, p, out)
                        return
                    p += 1
                return
            if p == n - 1:
                return
            if abs(loc.p.imag - x) > TOL or segs[p].e == loc.p:
                p += 1
                continue
            for ip in range(p, n):
                hits: list[float] = []
                segs[ip].intersection_z(loc.p.imag, hits)
                if not hits:
                    continue
                dest_z = hits[0] if ip != p else hits[-1]
                distance = abs(dest_z - loc.p.real)
                if dest_z - TOL > loc.p.real:
                    continue  # the diving curve at the starting point only
                if distance < TOL:
                    if p == ip:
                        continue
                    if abs(loc.p - segs[ip].s) < TOL:
                        p = ip  # another curve at its entry point
                        break
                    x -= self.delta  # a zero-length cut
                    break
                dest = complex(dest_z, loc.p.imag)
                out.straight(dest)
                scale = min(1.0, distance / 2 / self.escape.real)
                dest += scale * self.escape
                out.rapid(dest)
                out.rapid(loc.p - (scale * self.escape).conjugate())
                if p == 0:
                    out.rapid(loc.p)
                else:
                    out.straight(loc.p)
                x -= self.delta
                break

    def add_distance(self, distance: float) -> None:
        """Offset the profile (all but its lead-in) by ``distance`` away from the material."""
        first, last = self.segs[0], self.segs[-1]
        if ((first.e - first.s) / (last.s - first.s)).imag < 0:
            distance = -distance
        lead = self.segs.pop(0)
        current = 0.0
        while current != distance:
            self._step()
            step = min([1e9, *(s.radius() / 2 for s in self.segs), abs(distance - current)])
            if distance < 0:
                step = -step
            for s in self.segs:
                s.offset(step)
            segs = [s for s in self.segs if s.radius() >= 1e-3]
            k = 0
            while k < len(segs) - 1:  # connect the pieces that came apart by an arc
                a, b = segs[k], segs[k + 1]
                if (a.e - b.s).real > 1e-2:
                    sa, sb = a.dup(), b.dup()
                    sa.offset(-step)
                    sb.offset(-step)
                    segs.insert(k + 1, Arc(distance > 0, a.e, (sa.e + sb.s) / 2.0, b.s))
                    k += 1
                k += 1
            k = 0
            while k < len(segs) - 1:
                self._step()
                if not segs[k].monotonic():
                    if k > 0 and segs[k].radius() >= segs[k - 1].radius():
                        del segs[k - 1]
                    else:
                        del segs[k]
                    k = 0
                    if len(segs) < 2:
                        break
                if segs[k].radius() < 1e-3:
                    del segs[k]
                    k = 0
                    if len(segs) < 2:
                        break
                else:
                    intersect(segs[k], segs[k + 1])
                k += 1
            self.segs = segs
            if current + step == current:
                break  # nothing left to offset
            current += step
        segs = self.segs
        for k in range(len(segs) - 1):
            mid = (segs[k].e + segs[k + 1].s) / 2.0
            segs[k].e = segs[k + 1].s = mid
        lead.e = segs[0].s
        segs.insert(0, lead)
