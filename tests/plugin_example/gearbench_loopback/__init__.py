"""A minimal third-party drive family for gearbench: ``loopback``.

Not part of gearbench: it lives outside the package and is found only through
its entry point (``gearbench.drives``), as a vendor's plugin would be::

    [project.entry-points."gearbench.drives"]
    loopback = "gearbench_loopback:LoopbackNetwork"

The drives are the simulated bench stepped in-process (no bus at all), one
physics period per ``sample()``. Because it is a simulator it also does the
operator's mounting (``mount()``), which gearbench uses as the bench fixture.

Profile::

    bench:
      bus:
        family: loopback
        options: {plant: {motors: {in: {Kt: 0.0527}, out: {Kt: 0.0512}}}, seed: 3}
"""
from __future__ import annotations

from gearbench.drives.base import AxisConfig, Drive, DriveNetwork, Mode, Sample

MODES = {Mode.VELOCITY: "velocity", Mode.TORQUE: "torque"}


class LoopbackDrive(Drive):
    def __init__(self, network: "LoopbackNetwork", config: AxisConfig):
        super().__init__(config)
        self.network = network

    def enable(self, mode: Mode) -> None:
        self.network.world.set_mode(self.name, MODES[mode])

    def set_setpoint(self, value: float) -> None:
        self.network.world.set_setpoint(self.name, value)

    def quick_stop(self) -> None:
        self.network.world.set_mode(self.name, "velocity")   # setpoint resets to 0: brake to rest

    def disable(self) -> None:
        # like a drive's disable-operation option "decelerate, then remove power": the
        # motor must not coast into the next segment (there is no time between segments here)
        world = self.network.world
        world.set_mode(self.name, "velocity")
        for _ in range(2000):
            if abs(world.step()[self.name].velocity_rad_s) < 0.5:
                break
        world.set_mode(self.name, "off")

    def reset_fault(self) -> None:
        pass


class LoopbackNetwork(DriveNetwork):
    """The simulated bench's two axes, "in" and "out", called directly."""

    family = "loopback"
    opened_networks = 0          # how many were opened: lets a test prove this class ran

    def __init__(self, *, plant: dict | None = None, seed: int = 0, **options):
        super().__init__(plant=plant, seed=seed, **options)
        self.plant_dict = dict(plant or {})
        self.seed = int(seed)
        self.world = None

    def open(self) -> None:
        type(self).opened_networks += 1


    def add_drive(self, config: AxisConfig) -> Drive:
        self.drives[config.name] = LoopbackDrive(self, config)
        return self.drives[config.name]

    def start(self, period_s: float) -> None:
        from gearbench.sim import BenchWorld, PlantParams

        self.period_s = period_s
        plant = PlantParams.from_dict({"period_s": period_s, **self.plant_dict}, "bus.options.plant")
        self.world = BenchWorld(plant, seed=self.seed)
        self._k = 0

    def _sample(self) -> dict[str, Sample]:
        meas = self.world.step()
        self._k += 1             # own counter: braking steps in disable() are not samples
        k = self._k
        return {name: Sample(k, k * self.period_s, m.position_rad, m.velocity_rad_s, m.current_a)
                for name, m in meas.items() if name in self.drives}

    def mount(self, *, coupling: str, disk_kgm2: dict[str, float]) -> None:
        self.world.mount(coupling=coupling, disk_kgm2=disk_kgm2)

    def _close(self) -> None:
        self.world = None
