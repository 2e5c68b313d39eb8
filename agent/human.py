"""Human drivers: drive the ego car yourself with the keyboard or a gamepad, in a pygame window.

Both drivers show ``env.composite()`` (camera beside the top-down map) scaled x2 with a HUD strip
underneath: speed, route command, next traffic light, route completion and a red REC dot while
recording. They use nothing but what a real driver sees, so ``privileged = False``.

Keys (both drivers, the window must have focus):
  arrows / WASD   steer (left/right), throttle (up/W), brake (down/S)   [keyboard driver]
  P               pause / resume (``act`` returns zeros while paused)
  R               request a reset of the episode (``reset_requested``)
  Esc / Q         quit (``quit_requested``; closing the window does the same)

Sign convention: positive steer turns RIGHT (the map frame has y down, so positive steer is
clockwise on the map); positive ``throttle_brake`` accelerates, negative brakes.

The program calls ``update_hud(info, recording)`` after each ``env.step``; the next ``act`` processes
window events, draws the frame and returns the action. With ``realtime=True`` (the default) ``act``
also waits so the loop runs at the simulator's rate (1 / ``dt_s``), which is what a human needs.
"""

from __future__ import annotations

from typing import TYPE_CHECKING, Any

import numpy as np

if TYPE_CHECKING:
    from towndrive.envs.drive_env import DriveEnv

HUD_HEIGHT = 64
LIGHT_COLOURS = {"green": (40, 200, 70), "yellow": (240, 200, 30), "red": (230, 40, 40)}


def _approach(value: float, target: float, rate: float, dt: float) -> float:
    """Move ``value`` towards ``target`` by at most ``rate * dt``."""
    step = rate * dt
    if value < target:
        return min(target, value + step)
    return max(target, value - step)


def _ramp(value: float, target: float, rate: float, release_rate: float, dt: float) -> float:
    """Ramp towards ``target``: at ``rate`` away from zero, at ``release_rate`` back towards (and through) zero."""
    away = target != 0.0 and value * target >= 0.0 and abs(target) > abs(value)
    return _approach(value, target, rate if away else release_rate, dt)


class HumanWindow:
    """The pygame window shared by the human drivers: picture, HUD and the P / R / Esc / Q keys."""

    def __init__(self, scale: int = 2, title: str = "towndrive - human driver") -> None:
        self.scale = scale
        self.title = title
        self.surface: Any = None  # the pygame display surface once open
        self.paused = False
        self.reset_requested = False
        self.quit_requested = False
        self.held: set[int] = set()  # keys held down, tracked from KEYDOWN / KEYUP events
        self._env: DriveEnv | None = None
        self._fonts: dict[int, Any] = {}
        self._clock: Any = None
        self._hud: dict[str, Any] = {}
        self._recording = False
        self._action = np.zeros(2, np.float32)

    # ------------------------------------------------------------------ lifecycle
    def open(self, env: DriveEnv) -> None:
        """Bind to ``env`` (already reset) and open the window (sized to its composite) if needed."""
        import pygame

        self._env = env
        self.paused = False
        self.reset_requested = False
        self.held.clear()
        self._hud = {}
        pygame.display.init()
        pygame.font.init()
        image = env.composite()
        size = (image.shape[1] * self.scale, image.shape[0] * self.scale + HUD_HEIGHT)
        if self.surface is None or pygame.display.get_surface() is None or self.surface.get_size() != size:
            self.surface = pygame.display.set_mode(size)
            pygame.display.set_caption(self.title)
        if self._clock is None:
            self._clock = pygame.time.Clock()
        pygame.event.clear()

    def close(self) -> None:
        import pygame

        if self.surface is not None:
            self.surface = None
            pygame.display.quit()

    # ------------------------------------------------------------------ events
    def process_events(self) -> None:
        """Handle window events: keep ``held`` up to date and act on P, R, Esc / Q and window close."""
        import pygame

        for event in pygame.event.get():
            if event.type == pygame.QUIT or (hasattr(pygame, "WINDOWCLOSE") and event.type == pygame.WINDOWCLOSE):
                self.quit_requested = True
            elif event.type == pygame.KEYDOWN:
                self.held.add(event.key)
                if event.key == pygame.K_p:
                    self.paused = not self.paused
                elif event.key == pygame.K_r:
                    self.reset_requested = True
                elif event.key in (pygame.K_ESCAPE, pygame.K_q):
                    self.quit_requested = True
            elif event.type == pygame.KEYUP:
                self.held.discard(event.key)
            elif hasattr(pygame, "WINDOWFOCUSLOST") and event.type == pygame.WINDOWFOCUSLOST:
                self.held.clear()  # no KEYUP arrives for keys released while another window has focus

    # ------------------------------------------------------------------ HUD
    def update_hud(self, info: dict[str, Any], recording: bool = False) -> None:
        """Store the values shown in the HUD (drawn on the next frame)."""
        light = info.get("next_light")
        self._hud = {
            "speed_kmh": float(info.get("ego", {}).get("speed_mps", 0.0)) * 3.6,
            "command": str(info.get("command", "")),
            "light": None if light is None else (str(light.get("state", "")), float(light.get("distance_m", 0.0))),
            "completion": float(info.get("route", {}).get("completion", 0.0)),
        }
        self._recording = bool(recording)

    def _font(self, size: int) -> Any:
        import pygame

        if size not in self._fonts:
            self._fonts[size] = pygame.font.Font(None, size)  # pygame's bundled font: no system fonts needed
        return self._fonts[size]

    def draw(self, action: np.ndarray, fps: float | None = None) -> None:
        """Draw the current picture, the HUD and ``action``; flip; wait for ``fps`` if given."""
        import pygame

        if self.surface is None or self._env is None:
            return
        self._action = np.asarray(action, np.float32)
        image = self._env.composite()
        surf = pygame.surfarray.make_surface(np.ascontiguousarray(image.transpose(1, 0, 2)))
        view_w, view_h = image.shape[1] * self.scale, image.shape[0] * self.scale
        if (view_w, view_h + HUD_HEIGHT) != self.surface.get_size():  # the env's picture size changed
            self.surface = pygame.display.set_mode((view_w, view_h + HUD_HEIGHT))
        self.surface.blit(pygame.transform.scale(surf, (view_w, view_h)), (0, 0))
        self._draw_hud(view_w, view_h)
        if self.paused:
            self._draw_paused(view_w, view_h)
        pygame.display.flip()
        if fps:
            self._clock.tick(fps)

    def _text(self, text: str, pos: tuple[int, int], size: int = 30, colour: tuple[int, int, int] = (235, 235, 235)) -> int:
        """Blit ``text`` with its top-left at ``pos``; return the x just after it."""
        img = self._font(size).render(text, True, colour)
        self.surface.blit(img, pos)
        return pos[0] + img.get_width()

    def _draw_hud(self, width: int, top: int) -> None:
        import pygame

        s = self.surface
        pygame.draw.rect(s, (22, 24, 28), (0, top, width, HUD_HEIGHT))
        pygame.draw.line(s, (70, 70, 80), (0, top), (width, top), 2)
        hud = self._hud
        grey = (150, 150, 160)
        y1, y2 = top + 8, top + 38
        # speed, big
        speed = self._font(46).render(f"{hud.get('speed_kmh', 0.0):.1f}", True, (235, 235, 235))
        self.surface.blit(speed, (100 - speed.get_width(), y1))  # right-aligned so "km/h" stays put
        self._text("km/h", (106, y1 + 14), 24, grey)
        # route command
        x = 165
        self._text("command", (x, y1), 20, grey)
        self._text(hud.get("command", "-").upper() or "-", (x, y1 + 18), 32)
        # traffic light
        x = 315
        self._text("next light", (x, y1), 20, grey)
        light = hud.get("light")
        if light is None:
            self._text("none", (x, y1 + 18), 32, grey)
        else:
            state, dist = light
            pygame.draw.circle(s, LIGHT_COLOURS.get(state, grey), (x + 10, y1 + 30), 10)
            pygame.draw.circle(s, (10, 10, 10), (x + 10, y1 + 30), 10, 2)
            self._text(f"{state} {dist:.0f} m", (x + 26, y1 + 18), 32)
        # route completion with a small bar
        x = 505
        self._text("route", (x, y1), 20, grey)
        completion = min(1.0, max(0.0, hud.get("completion", 0.0)))
        self._text(f"{completion * 100:.1f} %", (x, y1 + 18), 32)
        pygame.draw.rect(s, (60, 60, 70), (x + 48, y1 + 2, 80, 12), 1)
        pygame.draw.rect(s, (80, 170, 255), (x + 49, y1 + 3, int(78 * completion), 10))
        # steer and throttle/brake bars (the action being applied)
        x = max(655, width - 160)
        steer, pedal = float(self._action[0]), float(self._action[1])
        self._text("steer", (x, y1), 20, grey)
        self._bar(x + 48, y1 + 2, 90, steer, (240, 240, 240))
        self._text("pedal", (x, y2 - 6), 20, grey)
        self._bar(x + 48, y2 - 4, 90, pedal, (60, 210, 90) if pedal >= 0 else (230, 60, 60))
        # REC, top right of the picture so it is seen even on a narrow window
        if self._recording:
            pygame.draw.rect(s, (20, 20, 20), (width - 92, 6, 84, 32), border_radius=6)
            pygame.draw.circle(s, (235, 30, 30), (width - 74, 22), 9)
            self._text("REC", (width - 58, 11), 30, (255, 60, 60))

    def _bar(self, x: int, y: int, w: int, value: float, colour: tuple[int, int, int]) -> None:
        """A centred bar for a value in [-1, 1]."""
        import pygame

        pygame.draw.rect(self.surface, (60, 60, 70), (x, y, w, 12), 1)
        mid = x + w // 2
        length = int(round(max(-1.0, min(1.0, value)) * (w // 2 - 1)))
        if length:
            pygame.draw.rect(self.surface, colour, (min(mid, mid + length), y + 1, abs(length), 10))
        pygame.draw.line(self.surface, (120, 120, 130), (mid, y - 2), (mid, y + 13))

    def _draw_paused(self, width: int, height: int) -> None:
        import pygame

        shade = pygame.Surface((width, height), pygame.SRCALPHA)
        shade.fill((0, 0, 0, 120))
        self.surface.blit(shade, (0, 0))
        img = self._font(64).render("PAUSED", True, (255, 255, 255))
        self.surface.blit(img, ((width - img.get_width()) // 2, height // 2 - img.get_height()))
        hint = self._font(26).render("P resume   R reset   Esc/Q quit", True, (220, 220, 220))
        self.surface.blit(hint, ((width - hint.get_width()) // 2, height // 2 + 8))


class _HumanDriver:
    """What the keyboard and gamepad drivers share: the window, its flags, pacing and ``act``."""

    name = "human"
    privileged = False

    def __init__(self, realtime: bool = True, scale: int = 2) -> None:
        self.realtime = realtime
        self.window = HumanWindow(scale=scale, title=f"towndrive - {self.name}")
        self.dt = 0.05
        self.action = np.zeros(2, np.float32)

    # flags the program polls
    @property
    def paused(self) -> bool:
        return self.window.paused

    @property
    def reset_requested(self) -> bool:
        return self.window.reset_requested

    @property
    def quit_requested(self) -> bool:
        return self.window.quit_requested

    def reset(self, env: DriveEnv) -> None:
        self.dt = float(env.config.world.dt_s)
        self.action = np.zeros(2, np.float32)
        self.window.open(env)

    def update_hud(self, info: dict[str, Any], recording: bool = False) -> None:
        self.window.update_hud(info, recording)

    def act(self, observation: dict[str, Any]) -> np.ndarray:
        self.window.process_events()
        if self.window.paused or self.window.quit_requested:
            out = np.zeros(2, np.float32)
        else:
            self.action = np.clip(self._control(), -1.0, 1.0).astype(np.float32)
            out = self.action.copy()
        self.window.draw(out, fps=1.0 / self.dt if self.realtime else None)
        return out

    def _control(self) -> np.ndarray:
        raise NotImplementedError

    def close(self) -> None:
        self.window.close()


class KeyboardDriver(_HumanDriver):
    """Arrows or WASD. Steering and pedals ramp at the given rates (per second) and return to zero faster."""

    name = "keyboard"
    privileged = False

    def __init__(self, steer_rate: float = 2.5, steer_return_rate: float = 5.0, throttle_rate: float = 2.0,
                 brake_rate: float = 3.0, pedal_return_rate: float = 5.0, realtime: bool = True, scale: int = 2) -> None:
        super().__init__(realtime=realtime, scale=scale)
        self.steer_rate = steer_rate
        self.steer_return_rate = steer_return_rate
        self.throttle_rate = throttle_rate
        self.brake_rate = brake_rate
        self.pedal_return_rate = pedal_return_rate
        self.steer = 0.0
        self.throttle_brake = 0.0

    def reset(self, env: DriveEnv) -> None:
        super().reset(env)
        self.steer = 0.0
        self.throttle_brake = 0.0

    def _control(self) -> np.ndarray:
        import pygame

        held = self.window.held
        left = bool(held & {pygame.K_LEFT, pygame.K_a})
        right = bool(held & {pygame.K_RIGHT, pygame.K_d})
        up = bool(held & {pygame.K_UP, pygame.K_w})
        down = bool(held & {pygame.K_DOWN, pygame.K_s})
        steer_target = float(right) - float(left)  # positive = right
        pedal_target = float(up) - float(down)
        self.steer = _ramp(self.steer, steer_target, self.steer_rate, self.steer_return_rate, self.dt)
        pedal_rate = self.throttle_rate if pedal_target > 0 else self.brake_rate
        self.throttle_brake = _ramp(self.throttle_brake, pedal_target, pedal_rate, self.pedal_return_rate, self.dt)
        return np.array([self.steer, self.throttle_brake], np.float32)


class GamepadDriver(_HumanDriver):
    """The first pygame joystick: left stick x steers, right trigger accelerates, left trigger brakes.

    Axis numbers differ between platforms and pads; the defaults (0, 5, 2) are an Xbox-style pad on
    Linux (on Windows it is usually ``throttle_axis=5, brake_axis=4``). Triggers read -1 released and
    +1 fully pressed and are mapped to [0, 1].
    """

    name = "gamepad"
    privileged = False

    def __init__(self, steer_axis: int = 0, throttle_axis: int = 5, brake_axis: int = 2, dead_zone: float = 0.08,
                 realtime: bool = True, scale: int = 2) -> None:
        super().__init__(realtime=realtime, scale=scale)
        self.steer_axis = steer_axis
        self.throttle_axis = throttle_axis
        self.brake_axis = brake_axis
        self.dead_zone = dead_zone
        self.joystick: Any = None

    def reset(self, env: DriveEnv) -> None:
        import pygame

        if self.joystick is None:
            pygame.joystick.init()
            if pygame.joystick.get_count() == 0:
                raise RuntimeError("No gamepad found; connect one or use --driver keyboard.")
            self.joystick = pygame.joystick.Joystick(0)
            self.joystick.init()
        super().reset(env)

    def _axis(self, index: int) -> float:
        if index >= self.joystick.get_numaxes():
            return 0.0
        return float(self.joystick.get_axis(index))

    def _trigger(self, index: int) -> float:
        return min(1.0, max(0.0, (self._axis(index) + 1.0) / 2.0))

    def _control(self) -> np.ndarray:
        x = self._axis(self.steer_axis)
        # dead zone, then rescale so the output still reaches +-1 and starts at 0 just outside it
        steer = 0.0 if abs(x) < self.dead_zone else np.sign(x) * (abs(x) - self.dead_zone) / (1.0 - self.dead_zone)
        pedal = self._trigger(self.throttle_axis) - self._trigger(self.brake_axis)
        return np.array([steer, pedal], np.float32)

    def close(self) -> None:
        super().close()
        self.joystick = None
