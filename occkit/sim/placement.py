"""Object placement: where the scene's objects go, proposed group by group in priority order.

:class:`Placer` walks the scene's layout and proposes the ego's lead and follower, road works, bus stops,
junction gear, buildings, street furniture, parked cars, riders, traffic streams and queues on every lane, and
pedestrians on the sidewalks and zebras. It only proposes; :func:`occkit.sim.selection.select` decides which
groups are kept.
"""

from __future__ import annotations

import math

import numpy as np

from occkit.sim.ground import BAY_DEPTH, OTHER_FLAT, SIDEWALK, TERRAIN
from occkit.sim.layout import Scene
from occkit.sim.objects import (
    Object,
    barrier,
    bicycle_rack,
    building,
    bus_shelter,
    cone,
    cycle,
    debris,
    hedge,
    pedestrian,
    pole,
    tree,
    vehicle,
    wall,
)
from occkit.sim.roads import LANE_WIDTH, SIGN, Crossing
from occkit.sim.selection import CHECK_MARGIN, EGO_RESERVE

__all__ = ["Placer"]

# Weights of the traffic-unit kinds in general traffic, as the ego's lead and as its follower; each kind's vehicles.
_TRAFFIC = {"car": 0.67, "truck": 0.12, "bus": 0.06, "truck_trailer": 0.07, "construction": 0.03, "motorcycle": 0.05}
_LEAD = {"car": 0.4, "truck_trailer": 0.3, "bus": 0.15, "truck": 0.15}
_FOLLOW = {"car": 0.5, "bus": 0.3, "truck": 0.2}
_UNITS = {
    "car": ("vehicle.car",),
    "truck": ("vehicle.truck",),
    "bus": ("vehicle.bus.rigid",),
    "truck_trailer": ("vehicle.truck", "vehicle.trailer"),
    "construction": ("vehicle.construction",),
    "motorcycle": ("vehicle.motorcycle",),
}
_HITCH = 0.8  # gap (m) between a truck and its trailer


def _unit_length(unit: list[Object]) -> float:
    """Bumper-to-bumper length (m) of a traffic unit."""
    return sum(o.size[1] for o in unit) + _HITCH * (len(unit) - 1)


class Placer:
    """Proposes the scene's objects, group by group, in priority order (earlier groups win conflicts)."""

    def __init__(self, scene: Scene) -> None:
        self.scene, self.rng, self.groups = scene, scene.rng, []
        self.paths = [scene.path] + [c.path for c in scene.crossings]
        self.density = scene.config.density
        ego = scene.ego
        self.ego_centre = tuple(float(scene.path.lane_to_centre(ego.s(t), ego.l)) for t in (0.0, scene.config.duration))

    def add(self, *objects: Object) -> None:
        """Propose ``objects`` as one group: kept or dropped together."""
        self.groups.append(list(objects))

    def uniform(self, lo: float, hi: float) -> float:
        """A float drawn uniformly from ``[lo, hi)``."""
        return float(self.rng.uniform(lo, hi))

    def choice(self, weights: dict[str, float]) -> str:
        """A key of ``weights`` drawn with probability proportional to its value."""
        names = list(weights)
        p = np.array([weights[n] for n in names])
        return names[int(self.rng.choice(len(names), p=p / p.sum()))]

    # ------------------------------------------------------------------------------------------ poses
    def on_main(self, obj: Object, s: float, l: float, turn: float = 0.0) -> Object:
        """Stand ``obj`` at main arc length ``s``, offset ``l``, yawed ``turn`` from the road's heading."""
        x, y, h = self.scene.path.point(s, l)
        obj.pose = (x, y, h + turn)
        return obj

    def on_crossing(self, obj: Object, c: Crossing, sc: float, lc: float, turn: float = 0.0) -> Object:
        """Stand ``obj`` at arc length ``sc``, offset ``lc`` of crossing ``c``, yawed ``turn`` from its heading."""
        x, y = c.xy(np.array(sc), np.array(lc))
        obj.pose = (float(x), float(y), math.atan2(c.u[1], c.u[0]) + turn)
        return obj

    def on_lane(self, obj: Object, path: int, l: float, s_lane: float, speed: float, direction: int) -> Object:
        """Put ``obj`` at lane arc length ``s_lane`` of path ``path`` at offset ``l``, heading ``direction`` (+-1)
        along it at ``speed`` m/s; a standing object gets a static pose."""
        if speed > 0.0:
            obj.track = (path, l, s_lane, direction * speed, direction < 0)
        else:
            x, y, h = self.paths[path].at_lane(np.array(s_lane), np.array(l))
            obj.pose = (float(x), float(y), float(h) + (np.pi if direction < 0 else 0.0))
        return obj

    def unit(self, kind: str, attribute: str) -> list[Object]:
        """The vehicles of one traffic unit (``_UNITS``), front first; motorcycles come with their riders."""
        return [
            cycle(self.rng, c, True) if c == "vehicle.motorcycle" else vehicle(self.rng, c, attribute)
            for c in _UNITS[kind]
        ]

    def drive(self, unit: list[Object], path: int, l: float, head: float, direction: int, speed: float):
        """Put a unit in a lane, its front end at lane arc length ``head``, its trailer behind it; returns it."""
        offset = 0.0
        for obj in unit:
            self.on_lane(obj, path, l, head - direction * (offset + obj.size[1] / 2), speed, direction)
            offset += obj.size[1] + _HITCH
        return unit

    def stream(self, path: int, l: float, direction: int, speed: float, lo: float, hi: float, limit: int = -1):
        """Up to ``limit`` (-1: any number of) units at one speed along a lane, at random gaps, spanning at most
        ``[lo, hi]`` of lane arc length at ``t = 0``."""
        attribute = "vehicle.moving" if speed > 0 else "vehicle.stopped"
        cursor = lo + self.uniform(0, 10) / self.density
        while limit != 0:
            unit = self.unit(self.choice(_TRAFFIC), attribute)
            length = _unit_length(unit)
            if cursor + length > hi:
                break
            head = cursor + length if direction > 0 else cursor
            self.add(*self.drive(unit, path, l + self.uniform(-0.15, 0.15), head, direction, speed))
            cursor += length + self.uniform(5, 35) / self.density
            limit -= 1

    def main_lane(self, s_centre, l):
        """Lane arc length at offset ``l`` of main arc length ``s_centre``."""
        return float(self.scene.path.centre_to_lane(s_centre, l))

    def view_lane(self, l: float, extra: float = 10.0) -> tuple[float, float]:
        """The scene's visible main arc-length range, widened by ``extra``, in lane arc length at offset ``l``."""
        lo, hi = self.scene.view
        return self.main_lane(lo - extra, l), self.main_lane(hi + extra, l)

    # ------------------------------------------------------------------------------------------ features
    def companions(self) -> None:
        """A lead vehicle and a follower in the ego's lane at the ego's mean speed: always in view."""
        ego = self.scene.ego
        reserve = EGO_RESERVE[1] + ego.deviation() + 2 * CHECK_MARGIN
        if self.rng.random() < 0.85:
            unit = self.unit(self.choice(_LEAD), "vehicle.moving")
            head = ego.s0 + EGO_RESERVE[0] + reserve + self.uniform(4, 16) + _unit_length(unit)
            self.add(*self.drive(unit, 0, ego.l, head, 1, ego.v))
        if self.rng.random() < 0.75:
            unit = self.unit(self.choice(_FOLLOW), "vehicle.moving")
            head = ego.s0 + EGO_RESERVE[0] - reserve - self.uniform(4, 14)
            self.add(*self.drive(unit, 0, ego.l, head, 1, ego.v))

    def works(self, side: int, s0: float, s1: float, closes_lane: bool) -> None:
        """Road works: a construction vehicle (often a trailer, sometimes a truck) fenced by barriers, cones
        tapering in from upstream, workers and debris. The zone takes the parking strip, sidewalk and terrain,
        and on multi-lane sides sometimes the outermost lane."""
        xsec, sign, rng = self.scene.xsec, SIGN[side], self.rng
        edge, kerb, outer = xsec.edge(side), xsec.kerb(side), xsec.outer(side)
        inner = edge - LANE_WIDTH + 0.4 if closes_lane else (edge + 0.3 if xsec.parking[side] > 0 else kerb + 0.2)
        far = outer + self.uniform(8, 12)
        mid = (s0 + s1) / 2
        turn = self.uniform(-0.3, 0.3)
        machine = vehicle(rng, "vehicle.construction", "vehicle.parked")
        w, l, _ = machine.size
        reach = l / 2 * abs(math.sin(turn)) + w / 2 * math.cos(turn)  # half extent across the road
        turn += np.pi if rng.random() < 0.5 else 0.0
        self.add(self.on_main(machine, mid + self.uniform(-2, 2), sign * (inner + 0.5 + reach), turn))
        if rng.random() < 0.85:
            trailer = vehicle(rng, "vehicle.trailer", "vehicle.parked")
            self.add(self.on_main(trailer, mid, sign * (far - 0.4 - trailer.size[0] / 2)))
        if rng.random() < 0.5:  # a truck parked behind the sidewalk just past the zone
            truck = vehicle(rng, "vehicle.truck", "vehicle.parked")
            past = s1 + 1.0 + truck.size[1] / 2 if side == 0 else s0 - 1.0 - truck.size[1] / 2
            self.add(self.on_main(truck, past, sign * (outer + 1.0 + truck.size[0] / 2), turn))
        for k in range(int((s1 - s0) / 2.6)):
            self.add(self.on_main(barrier(rng), s0 + 1.3 + 2.6 * k, sign * (inner + 0.3), np.pi / 2))
        for s_end in (s0, s1):
            lateral = inner + 1.6
            while lateral + 1.3 < far:
                self.add(self.on_main(barrier(rng), s_end, sign * lateral))
                lateral += 2.6
        upstream, start = (-1.0, s0) if side == 0 else (1.0, s1)
        target = edge - 0.3 if closes_lane else inner + 0.1
        count = int(rng.integers(4, 8))
        for q in range(1, count + 1):
            lateral = inner + 0.1 + (target - inner - 0.1) * q / count
            self.add(self.on_main(cone(rng), start + upstream * 2.0 * q, sign * lateral))
        for _ in range(int(rng.integers(2, 5))):
            self.add(self.on_main(cone(rng), self.uniform(s0 + 1, s1 - 1), sign * self.uniform(inner + 1, far - 1)))
        for _ in range(int(rng.integers(1, 4))):
            worker = pedestrian(rng, False, "human.pedestrian.construction_worker")
            s, lat = self.uniform(s0 + 1, s1 - 1), self.uniform(inner + 1, far - 1)
            self.add(self.on_main(worker, s, sign * lat, self.uniform(-np.pi, np.pi)))
        for _ in range(int(rng.integers(1, 4))):
            s, lat = self.uniform(s0 + 1, s1 - 1), self.uniform(inner + 1, far - 1)
            self.add(self.on_main(debris(rng), s, sign * lat, self.uniform(-np.pi, np.pi)))

    def bus_stop(self, side: int, s: float, in_bay: bool) -> None:
        """A shelter behind the sidewalk, people waiting, and usually a bus at the kerb (in its bay if any)."""
        xsec, sign, rng = self.scene.xsec, SIGN[side], self.rng
        turn = 0.0 if side == 0 else np.pi
        if rng.random() < 0.9:
            bus = vehicle(rng, "vehicle.bus.rigid", "vehicle.stopped")
            w = bus.size[0]
            lateral = xsec.edge(side) + BAY_DEPTH - 0.25 - w / 2 if in_bay else xsec.edge(side) - 0.35 - w / 2
            self.add(self.on_main(bus, s, sign * lateral, turn))
        self.add(self.on_main(bus_shelter(rng), s, sign * (xsec.outer(side) + 0.9), turn))
        for _ in range(int(rng.integers(1, 5))):
            person = pedestrian(rng, False)
            lateral = xsec.outer(side) - self.uniform(0.4, 1.2)
            self.add(self.on_main(person, s + self.uniform(-4, 4), sign * lateral, self.uniform(-np.pi, np.pi)))

    def junctions(self) -> None:
        """Traffic lights on the corners of each junction; barriers closing crossing roads that end."""
        xsec, rng, lo, hi = self.scene.xsec, self.rng, self.scene.bbox[:2], self.scene.bbox[2:]
        for c in self.scene.crossings:
            skew = math.sqrt(max(1.0 - float(np.dot(c.u, c.tangent)) ** 2, 0.5))
            for side in (0, 1):
                sc = SIGN[side] * (xsec.kerb(side) + 0.4) / skew
                for lc in (-1.0, 1.0):
                    light = pole(rng, "traffic_light", 0.0)
                    self.add(self.on_crossing(light, c, sc, lc * (c.half_width + c.sidewalk + 0.6)))
            for end in (-c.minus + 0.6, c.plus - 0.6):
                point = c.xy(np.array(end), np.array(0.0))
                if np.all((point > lo) & (point < hi)):
                    for lc in (-2.6, 0.0, 2.6):
                        self.add(self.on_crossing(barrier(rng), c, end, lc))

    def buildings(self) -> None:
        """Rows of buildings set back behind the sidewalks of the main road and of the crossing arms."""
        scene, rng = self.scene, self.rng
        for side in (0, 1):
            s = scene.view[0] - 10 + self.uniform(0, 10)
            while s < scene.view[1] + 10:
                width, depth = self.uniform(8, 30), self.uniform(8, 20)
                lateral = scene.xsec.outer(side) + self.uniform(2, 10) + depth / 2
                self.add(self.on_main(building(rng, scene.style, width, depth), s + width / 2, SIGN[side] * lateral))
                s += width + self.uniform(1, 10)
        for c in scene.crossings:
            for arm, side, length in ((-1.0, 0, c.minus), (1.0, 1, c.plus)):
                for lc_sign in (-1.0, 1.0):
                    s = scene.xsec.outer(side) + self.uniform(6, 12)
                    while s < length:
                        width, depth = self.uniform(8, 30), self.uniform(8, 20)
                        lc = lc_sign * (c.half_width + c.sidewalk + self.uniform(2, 10) + depth / 2)
                        self.add(
                            self.on_crossing(building(rng, scene.style, width, depth), c, arm * (s + width / 2), lc)
                        )
                        s += width + self.uniform(1, 10)

    def furniture(self) -> None:
        """Street trees, lights, signs and poles at the kerb; hedges, trees, walls, bicycle racks, parked
        motorcycles and debris beyond the sidewalks; barriers on a stretch of median; the same on crossing arms."""
        scene, rng, xsec = self.scene, self.rng, self.scene.xsec
        lo, hi = scene.view
        green, dens = scene.style.trees, self.density
        for side in (0, 1):
            sign, kerb, outer = SIGN[side], xsec.kerb(side), xsec.outer(side)
            turn = 0.0 if side == 0 else np.pi
            road = 1.0 if side == 0 else -1.0  # local y of the road seen from a pole, in the road's frame
            for s in self.steps(lo, hi, 8, 18, green * dens):
                if rng.random() < 0.6:
                    self.add(self.on_main(tree(rng, True), s, sign * (kerb + 0.55)))
            for s in self.steps(lo, hi, 25, 40, 1.0):
                self.add(self.on_main(pole(rng, "street_light", road), s, sign * (kerb + 0.35)))
            for s in self.steps(lo, hi, 15, 45, 1.0):
                kind = "sign" if rng.random() < 0.6 else "pole"
                self.add(self.on_main(pole(rng, kind, road), s, sign * (kerb + 0.3)))
            for s in self.steps(lo, hi, 6, 16, green * dens):
                lateral = outer + self.uniform(1.0, 4.5)
                item = tree(rng, False) if rng.random() < 0.5 else hedge(rng)
                self.add(self.on_main(item, s, sign * lateral))
            for s in self.steps(lo, hi, 15, 40, 1.0):
                if rng.random() < 0.4:
                    self.add(self.on_main(wall(rng, self.uniform(5, 15)), s, sign * (outer + self.uniform(0.3, 1.0))))
            for s in self.steps(lo, hi, 12, 35, dens):
                lateral = kerb + self.uniform(0.2, 0.6) if rng.random() < 0.5 else outer + self.uniform(0.3, 3.0)
                self.add(self.on_main(debris(rng), s, sign * lateral, self.uniform(-np.pi, np.pi)))
            for s in self.steps(lo, hi, 35, 70, 1.0):
                self.bicycle_rack(side, s, turn)
            for s in self.steps(lo, hi, 40, 80, 1.0):
                self.motorcycle_row(side, s)
        if xsec.median > 0 and rng.random() < 0.5:
            start = self.ego_centre[0] + self.uniform(-20, 60)
            for k in range(int(self.uniform(15, 40) / 2.6)):
                self.add(self.on_main(barrier(rng), start + 2.6 * k, 0.0, np.pi / 2))
        for c in scene.crossings:
            for arm, side, length in ((-1.0, 0, c.minus), (1.0, 1, c.plus)):
                for lc_sign in (-1.0, 1.0):
                    for s in self.steps(xsec.outer(side) + 4, length, 10, 25, green * dens):
                        self.add(self.on_crossing(tree(rng, True), c, arm * s, lc_sign * (c.half_width + 0.5)))
                    for s in self.steps(xsec.outer(side) + 4, length, 25, 40, 1.0):
                        light = pole(rng, "street_light", -lc_sign)
                        self.add(self.on_crossing(light, c, arm * s, lc_sign * (c.half_width + 0.35)))

    def steps(self, lo: float, hi: float, step_lo: float, step_hi: float, density: float) -> list[float]:
        """Positions from ``lo`` to ``hi`` at random steps in ``[step_lo, step_hi] / density``."""
        out, s = [], lo + self.uniform(0, step_lo)
        while s < hi:
            out.append(s)
            s += self.uniform(step_lo, step_hi) / density
        return out

    def bicycle_rack(self, side: int, s: float, turn: float) -> None:
        """A rack on the terrain behind the sidewalk with bicycles parked across it."""
        sign, outer, rng = SIGN[side], self.scene.xsec.outer(side), self.rng
        length = self.uniform(2.0, 4.0)
        self.add(self.on_main(bicycle_rack(rng, length), s, sign * (outer + 2.0), turn))
        bikes = []
        for k in range(int(rng.integers(1, int(length / 0.8) + 1))):
            bike = cycle(rng, "vehicle.bicycle", False)
            bikes.append(self.on_main(bike, s - length / 2 + 0.4 + 0.8 * k, sign * (outer + 0.95), np.pi / 2))
        self.add(*bikes)

    def motorcycle_row(self, side: int, s: float) -> None:
        """Parked motorcycles: in a row along the parking strip, or side by side behind the sidewalk."""
        xsec, sign, rng = self.scene.xsec, SIGN[side], self.rng
        for k in range(int(rng.integers(1, 5))):
            moto = cycle(rng, "vehicle.motorcycle", False)
            if xsec.parking[side] > 0 and rng.random() < 0.5:
                moto.ground = (OTHER_FLAT,)
                self.add(self.on_main(moto, s + 2.6 * k, sign * (xsec.edge(side) + xsec.parking[side] / 2)))
            else:
                moto.ground = (SIDEWALK, TERRAIN)
                self.add(self.on_main(moto, s + 1.1 * k, sign * (xsec.outer(side) + 1.3), np.pi / 2))

    def parked(self) -> None:
        """Cars parked along the parking strips, facing the traffic of their side."""
        scene = self.scene
        for side in (0, 1):
            width = scene.xsec.parking[side]
            if width == 0:
                continue
            lateral = SIGN[side] * (scene.xsec.edge(side) + width / 2)
            s = scene.view[0] + self.uniform(0, 5)
            while s < scene.view[1]:
                car = vehicle(self.rng, "vehicle.car", "vehicle.parked")
                car.ground = (OTHER_FLAT,)
                length = car.size[1]
                self.add(self.on_main(car, s + length / 2, lateral, 0.0 if side == 0 else np.pi))
                s += length + self.uniform(0.8, 8.0) / self.density

    def riders(self) -> None:
        """Cyclists and motorcyclists riding near the road edge, with their side's traffic."""
        xsec, rng = self.scene.xsec, self.rng
        for side in (0, 1):
            direction = 1 if side == 0 else -1
            for category, speeds in (("vehicle.bicycle", (3, 7)), ("vehicle.motorcycle", (6, 13))):
                for _ in range(int(rng.poisson(1.0 * self.density))):
                    bike = cycle(rng, category, True)
                    l = SIGN[side] * (xsec.edge(side) - 0.45 - bike.size[0] / 2)
                    s = self.main_lane(self.uniform(*self.scene.view), l)
                    self.add(self.on_lane(bike, 0, l, s, self.uniform(*speeds), direction))

    def main_traffic(self) -> None:
        """Every lane of the main road: a stream at one speed per lane (the ego's speed in its lane), or a queue
        stopped at a junction; only vehicles that get into view at some instant."""
        scene, xsec = self.scene, self.scene.xsec
        ego, duration = scene.ego, scene.config.duration
        for side in (0, 1):
            direction = 1 if side == 0 else -1
            for j in range(xsec.lanes[side]):
                l = xsec.lane(side, j)
                if side == 0 and j == scene.ego_side_lane:
                    speed = ego.v
                elif self.rng.random() < 0.2 and self.queue(side, l, direction):
                    continue
                else:
                    speed = self.uniform(3, 14)
                a, b = self.view_lane(l)
                travel = direction * speed * duration
                self.stream(0, l, direction, speed, min(a, a - travel), max(b, b - travel))

    def queue(self, side: int, l: float, direction: int) -> bool:
        """Stop a queue of 2..6 vehicles at the junction nearest the ego's path; False if none is in view."""
        scene = self.scene
        middle = sum(self.ego_centre) / 2
        near = [c for c in scene.crossings if scene.view[0] + 30 < c.s_main < scene.view[1] - 30]
        if not near:
            return False
        c = min(near, key=lambda c: abs(c.s_main - middle))
        skew = math.sqrt(max(1.0 - float(np.dot(c.u, c.tangent)) ** 2, 0.5))
        head = self.main_lane(c.s_main - direction * ((c.half_width + c.sidewalk + 1.5) / skew + 1.0), l)
        for _ in range(int(self.rng.integers(2, 7))):
            unit = self.drive(self.unit(self.choice(_TRAFFIC), "vehicle.stopped"), 0, l, head, direction, 0.0)
            self.add(*unit)
            head -= direction * (_unit_length(unit) + self.uniform(1.5, 3.0))
        return True

    def arm_limits(self, c: Crossing, lc: float, limits: tuple[float, float]) -> tuple[float, float]:
        """Where a line of the crossing at offset ``lc`` comes within ``limits[side]`` of the main road's centreline:
        ``(sc`` where it enters, ``sc`` where it leaves``)``."""
        sc = np.arange(-c.minus, c.plus, 0.25)
        _, l = self.scene.path.project(c.xy(sc, np.full_like(sc, lc)))
        inside = np.flatnonzero(np.abs(l) <= np.where(l < 0, limits[0], limits[1]))
        return float(sc[inside[0]]) - 0.25, float(sc[inside[-1]]) + 0.25

    def crossing_traffic(self) -> None:
        """Per crossing lane: a queue waiting at the stop line of the arm heading to the junction, vehicles
        leaving on the other arm; none of them enters the junction during the scene."""
        xsec, duration, rng = self.scene.xsec, self.scene.config.duration, self.rng
        for index, c in enumerate(self.scene.crossings):
            path = index + 1
            for lc in (-LANE_WIDTH / 2, LANE_WIDTH / 2):
                direction = 1 if lc < 0 else -1
                stop_minus, stop_plus = self.arm_limits(c, lc, (xsec.outer(0) + 1.0, xsec.outer(1) + 1.0))
                head = (stop_minus - 0.3 if direction > 0 else stop_plus + 0.3) + c.minus
                for _ in range(int(rng.integers(0, 4))):
                    unit = self.unit(self.choice(_TRAFFIC), "vehicle.stopped")
                    self.add(*self.drive(unit, path, lc, head, direction, 0.0))
                    head -= direction * (_unit_length(unit) + self.uniform(1.5, 3.0))
                speed = self.uniform(3, 12)
                lo, hi = (stop_plus, c.plus) if direction > 0 else (-c.minus, stop_minus)
                lo, hi = (lo, hi - speed * duration) if direction > 0 else (lo + speed * duration, hi)
                self.stream(path, lc, direction, speed, lo + c.minus, hi + c.minus, limit=int(rng.integers(0, 4)))

    def pedestrians(self) -> None:
        """People walking (0.5..1.8 m/s) or standing on the sidewalks, and crossing on the zebras."""
        scene, xsec, rng = self.scene, self.scene.xsec, self.rng
        duration = scene.config.duration
        for side in (0, 1):
            kerb, outer = xsec.kerb(side), xsec.outer(side)
            walk = kerb + 0.9  # the kerb side of the sidewalk holds the street furniture
            lines = [walk + 0.45, outer - 0.45] if outer - walk >= 1.9 else [(walk + outer) / 2]
            for lateral in lines:
                l = SIGN[side] * lateral
                a, b = self.view_lane(l)
                for s in self.steps(a, b, 5, 25, self.density):
                    self.walker(0, l, s)
        for index, c in enumerate(scene.crossings):
            for lc_sign in (-1.0, 1.0):
                lc = lc_sign * (c.half_width + 0.7 + (c.sidewalk - 0.7) / 2)
                enter, leave = self.arm_limits(c, lc, (xsec.edge(0) + 0.5, xsec.edge(1) + 0.5))
                for lo, hi in ((-c.minus, enter), (leave, c.plus)):
                    for s in self.steps(lo, hi, 8, 25, self.density):
                        speed, direction = self.uniform(0.5, 1.8), 1 if rng.random() < 0.5 else -1
                        end = s + direction * speed * duration
                        if lo + 0.5 < min(s, end) and max(s, end) < hi - 0.5:
                            self.add(self.on_lane(pedestrian(rng, True), index + 1, lc, s + c.minus, speed, direction))
                zebra = lc_sign * (c.half_width + c.sidewalk / 2)
                enter, leave = self.arm_limits(c, zebra, (xsec.edge(0), xsec.edge(1)))
                for _ in range(int(rng.integers(0, 3))):
                    speed, direction = self.uniform(1.0, 1.6), 1 if rng.random() < 0.5 else -1
                    s = self.uniform(enter, leave) + c.minus
                    self.add(self.on_lane(pedestrian(rng, True), index + 1, zebra, s, speed, direction))

    def walker(self, path: int, l: float, s: float) -> None:
        """Someone at lane arc length ``s`` of a sidewalk line: mostly walking either way, sometimes standing."""
        rng = self.rng
        if rng.random() < 0.15:
            person = self.on_lane(pedestrian(rng, False), path, l, s, 0.0, 1)
            person.pose = (*person.pose[:2], self.uniform(-np.pi, np.pi))
        else:
            person = self.on_lane(
                pedestrian(rng, True), path, l, s, self.uniform(0.5, 1.8), 1 if rng.random() < 0.5 else -1
            )
        self.add(person)
