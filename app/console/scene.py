"""The console's 3D scene (metres; core's mm are converted here): the UR3 on its joint angles,
the flange and the image plane it carries, the phantom, the registered markers, the test object,
the reconstructed surface and a self-check's views, in layers shown, hidden or faded as wholes.
Handles are server-wide, so every tab sees the same scene."""

from __future__ import annotations

import numpy as np
import trimesh
import viser
import viser.transforms as vtf

from probecal.app.console.draw import (
    LABEL_COLOUR,
    box_edges,
    cylinder_pose,
    fan_texture,
    image_centre_pose,
    image_outline,
)
from probecal.core.geometry.fan import Fan
from probecal.core.geometry.phantom import Phantom
from probecal.core.geometry.transforms import transform_points
from probecal.core.robot.ur3 import UR3
from probecal.core.volume.pointcloud import error_colors

MM = 1e-3
LINK_RADIUS = 0.022
ARM_COLOR = (120, 150, 190)
JOINT_COLOR = (70, 80, 95)
WIRE_COLOR = (40, 90, 230)
REGISTRATION_FULL_SCALE_MM = 1.0
"""Registered markers are coloured blue (on their wire) to red (this far off, mm, or more)."""
ROBOT_CAMERA = (0.42, -0.72, 0.22)
ROBOT_LOOK_AT = (-0.02, -0.2, 0.02)
"""The whole-robot view (m, base frame)."""
PROBE_COLOR = (190, 195, 205)
PROBE_OPACITY = 0.45
PROBE_THICKNESS_MM = 16.0
PROBE_MARGIN_MM = 6.0
SCENE_IMAGE_WIDTH_PX = 192
TARGET_COLOR, NEXT_COLOR, LIVE_COLOR = (120, 200, 140), (240, 140, 0), (190, 75, 219)
"""The guidance's targets still to reach, the next one, and the live image."""
LAYERS = ("robot", "probe", "image plane", "phantom", "wires", "markers", "guidance", "cloud", "self-check",
          "CAD model", "volume", "slices")
"""What the scene draws, each layer shown or hidden as a whole (the panel's View step)."""
FADED_OPACITY = 0.2
"""A faded layer: drawn faintly so that what it would hide shows through (an image plane faded
shows its outline alone)."""


def _wxyz(rotation: np.ndarray) -> np.ndarray:
    return vtf.SO3.from_matrix(rotation).wxyz


class Scene:
    """Creates the scene once and updates it in place."""

    def __init__(self, server: viser.ViserServer, phantom: Phantom, image_size_px: tuple[int, int],
                 fan: Fan | None = None):
        self.server = server
        self.width_px, self.height_px = image_size_px
        self.fan = fan  # a fan image's, in its pixels: the plane is drawn as the fan it is
        scene = server.scene
        scene.configure_environment_map(hdri=None)
        scene.configure_default_lights(cast_shadow=False)
        scene.set_up_direction("+z")
        server.initial_camera.position = ROBOT_CAMERA
        server.initial_camera.look_at = ROBOT_LOOK_AT
        scene.add_grid("/floor", width=0.8, height=0.8, cell_size=0.05, section_size=0.25,
                       position=(0.0, -0.2, -0.09), shadow_opacity=0.0)
        scene.add_frame("/base", axes_length=0.08, axes_radius=0.004)
        # The arm as a kinematic tree of its DH links: moving it only turns the six joint nodes.
        self.joints, parent = [], "/robot"
        self.arm: list[viser.IcosphereHandle | viser.CylinderHandle] = [
            scene.add_icosphere("/robot/base", radius=LINK_RADIUS * 1.4, color=JOINT_COLOR, cast_shadow=False)]
        for i in range(6):
            joint = scene.add_frame(f"{parent}/j{i + 1}", show_axes=False)
            self.joints.append(joint)
            offset = np.array([UR3.a[i], 0.0, UR3.d[i]])
            rotation, length = cylinder_pose(np.zeros(3), offset)
            self.arm.append(scene.add_cylinder(f"{joint.name}/link", radius=LINK_RADIUS, height=length * MM,
                                               color=ARM_COLOR, wxyz=_wxyz(rotation), position=offset / 2 * MM,
                                               cast_shadow=False, receive_shadow=False))
            link = scene.add_frame(f"{joint.name}/l", show_axes=False, position=offset * MM,
                                   wxyz=vtf.SO3.from_x_radians(UR3.alpha[i]).wxyz)
            self.arm.append(scene.add_icosphere(f"{link.name}/ball", radius=LINK_RADIUS * 1.3, color=JOINT_COLOR,
                                                cast_shadow=False, receive_shadow=False))
            parent = link.name
        self.flange = scene.add_frame(f"{parent}/flange", axes_length=0.05, axes_radius=0.003)
        self.outline = scene.add_line_segments(f"{self.flange.name}/image_outline",
                                               image_outline(np.eye(4), self.width_px, self.height_px, fan) * 0.0,
                                               colors=(250, 160, 40), thickness=2.0, thickness_units="screen")
        self.probe: viser.BoxHandle | None = None
        self.plane_image = scene.add_image(f"{self.flange.name}/image", np.zeros((2, 2), np.uint8), render_width=0.01,
                                           render_height=0.01, format="png", visible=False)
        self.phantom = scene.add_frame("/phantom", show_axes=False)
        self.phantom_box = scene.add_line_segments("/phantom/box", box_edges(phantom.box_min, phantom.box_max) * MM,
                                                   colors=(150, 150, 150), thickness=1.5, thickness_units="screen")
        self.wires = scene.add_line_segments("/phantom/wires", phantom.lines() * MM, colors=WIRE_COLOR,
                                             thickness=2.5, thickness_units="screen")
        self.wires_off = scene.add_line_segments("/phantom/wires_off", np.zeros((1, 2, 3)), colors=(224, 49, 49),
                                                 thickness=4.0, thickness_units="screen", visible=False)
        # Guidance of a tracked probe, in the phantom's frame: the targets (the next one bold) and
        # the image where its own dots place it.
        self.targets = scene.add_line_segments("/phantom/targets", np.zeros((1, 2, 3)), colors=TARGET_COLOR,
                                               thickness=1.5, thickness_units="screen", visible=False)
        self.next_target = scene.add_line_segments("/phantom/next_target", np.zeros((1, 2, 3)), colors=NEXT_COLOR,
                                                   thickness=4.0, thickness_units="screen", visible=False)
        self.live_image = scene.add_line_segments("/phantom/live_image", np.zeros((1, 2, 3)), colors=LIVE_COLOR,
                                                  thickness=3.0, thickness_units="screen", visible=False)
        self._has_guide = False
        self.registration = scene.add_point_cloud("/registration", np.zeros((1, 3)), colors=(0, 0, 0),
                                                  point_size=0.0018, point_shape="circle", visible=False)
        self.object: viser.GlbHandle | None = None
        self.cloud: viser.PointCloudHandle | None = None
        self.views: list[viser.PointCloudHandle] = []  # a self-check's surfaces, one per view
        self.live: viser.PointCloudHandle | None = None
        self.slices: viser.LineSegmentsHandle | None = None
        self.shown = dict.fromkeys(LAYERS, True)
        self.faded: set[str] = set()
        self._has_texture = self._has_markers = self._has_wires_off = False

    def show_layer(self, layer: str, shown: bool) -> None:
        """Show or hide one of :data:`LAYERS` as a whole (what it draws stays, to be shown again)."""
        self.shown[layer] = shown
        self._apply()

    def fade(self, layers: set[str]) -> None:
        """Draw ``layers`` (robot, probe, image plane) faintly, and the others as they are."""
        self.faded = set(layers)
        self._apply()

    def _apply(self) -> None:
        """Every handle visible as its layer is shown, and has something to draw."""
        shown, faded = self.shown, self.faded
        for handle in self.arm:
            handle.visible = shown["robot"]
            handle.opacity = FADED_OPACITY if "robot" in faded else None
        if self.probe is not None:
            self.probe.visible = shown["probe"]
            self.probe.opacity = FADED_OPACITY if "probe" in faded else PROBE_OPACITY
        self.outline.visible = shown["image plane"]
        self.plane_image.visible = shown["image plane"] and self._has_texture and "image plane" not in faded
        self.phantom_box.visible = shown["phantom"]
        self.wires.visible = shown["wires"]
        self.wires_off.visible = shown["wires"] and self._has_wires_off
        self.registration.visible = shown["markers"] and self._has_markers
        for guide in (self.targets, self.next_target, self.live_image):
            guide.visible = shown["guidance"] and self._has_guide
        for drawn, layer in ((self.cloud, "cloud"), (self.object, "CAD model"), (self.live, "volume"),
                             (self.slices, "slices"), *((view, "self-check") for view in self.views)):
            if drawn is not None:
                drawn.visible = shown[layer]

    def set_robot(self, joints: np.ndarray) -> None:
        """Turn the arm's joints to angles (rad)."""
        for handle, q in zip(self.joints, joints):
            handle.wxyz = vtf.SO3.from_z_radians(float(q)).wxyz

    def _set_probe(self, image_to_tool: np.ndarray) -> None:
        """The probe's body: a box from the flange to the top edge of the image (the transducer),
        as wide as the image, its x along the image's columns."""
        top = (image_to_tool @ np.array([self.width_px / 2, 0.0, 0.0, 1.0]))[:3]
        length = float(np.linalg.norm(top))
        z = top / length
        x = image_to_tool[:3, 0] - (image_to_tool[:3, 0] @ z) * z
        x /= np.linalg.norm(x)
        width = float(np.linalg.norm(image_to_tool[:3, 0])) * self.width_px + PROBE_MARGIN_MM
        if self.probe is not None:
            self.probe.remove()
        dimensions = (width * MM, PROBE_THICKNESS_MM * MM, length * MM)
        self.probe = self.server.scene.add_box(
            f"{self.flange.name}/probe", color=PROBE_COLOR, dimensions=dimensions, opacity=PROBE_OPACITY,
            wxyz=_wxyz(np.column_stack([x, np.cross(z, x), z])), position=top / 2 * MM, cast_shadow=False,
            receive_shadow=False, visible=self.shown["probe"])

    def set_image_mount(self, image_to_tool: np.ndarray) -> None:
        """Put the image plane where ``image_to_tool`` (pixels to tool mm) says it is, and the
        probe between it and the flange."""
        self._set_probe(image_to_tool)
        self.outline.points = (image_outline(image_to_tool, self.width_px, self.height_px, self.fan)
                               * MM).astype(np.float32)
        pose = image_centre_pose(image_to_tool, self.width_px, self.height_px)
        self.plane_image.wxyz = _wxyz(pose[:3, :3])
        self.plane_image.position = pose[:3, 3] * MM
        self.plane_image.render_width = float(np.linalg.norm(image_to_tool[:3, 0])) * self.width_px * MM
        self.plane_image.render_height = float(np.linalg.norm(image_to_tool[:3, 1])) * self.height_px * MM

    def set_plane_texture(self, image: np.ndarray) -> None:
        """Show a recorded frame on the image plane (downsampled: it is small on screen; a fan
        image's clear outside its fan)."""
        step = max(1, image.shape[1] // SCENE_IMAGE_WIDTH_PX)
        self.plane_image.image = np.ascontiguousarray(fan_texture(image, self.fan)[::step, ::step])
        if not self._has_texture:
            self._has_texture = True
            self._apply()

    def set_phantom_pose(self, phantom_to_base: np.ndarray) -> None:
        self.phantom.wxyz = _wxyz(phantom_to_base[:3, :3])
        self.phantom.position = phantom_to_base[:3, 3] * MM

    def set_registration(self, points_base_mm: np.ndarray, distances_mm: np.ndarray,
                         full_scale_mm: float = REGISTRATION_FULL_SCALE_MM) -> None:
        """Registered markers (base mm), coloured blue (on the wire) to red (``full_scale_mm`` or more off)."""
        self._has_markers = len(points_base_mm) > 0
        if self._has_markers:
            self.registration.points = (points_base_mm * MM).astype(np.float32)
            self.registration.colors = error_colors(distances_mm, full_scale_mm)
        self.registration.visible = self.shown["markers"] and self._has_markers

    def set_guide(self, targets_mm: np.ndarray, next_mm: np.ndarray | None, live_mm: np.ndarray | None) -> None:
        """The targets still to reach, (K, N, 2, 3) outlines of their images in the phantom's frame
        (mm), the next one's and the live image's ((N, 2, 3), None: none)."""
        self._has_guide = True
        empty = np.zeros((1, 2, 3), np.float32)
        self.targets.points = (targets_mm.reshape(-1, 2, 3) * MM).astype(np.float32) if len(targets_mm) else empty
        self.next_target.points = empty if next_mm is None else (next_mm * MM).astype(np.float32)
        self.live_image.points = empty if live_mm is None else (live_mm * MM).astype(np.float32)
        self._apply()

    def set_wires_off(self, lines_mm: np.ndarray) -> None:
        """Wires found off their definition, (W, 2, 3) end points in the phantom frame (mm), in red
        (part of the wires layer)."""
        self.wires_off.points = (lines_mm * MM).astype(np.float32) if len(lines_mm) else np.zeros((1, 2, 3),
                                                                                                  np.float32)
        self._has_wires_off = len(lines_mm) > 0
        self._apply()

    def set_object(self, mesh: trimesh.Trimesh, object_to_base: np.ndarray) -> None:
        """The volume target's CAD model where it is believed to sit, translucent."""
        if self.object is not None:
            self.object.remove()
        shown = mesh.copy()
        shown.apply_transform(object_to_base)
        shown.apply_scale(MM)
        shown.visual = trimesh.visual.ColorVisuals(shown, face_colors=(200, 200, 200, 90))
        self.object = self.server.scene.add_mesh_trimesh("/object", shown, cast_shadow=False, receive_shadow=False,
                                                         visible=self.shown["CAD model"])

    def set_cloud(self, points_base_mm: np.ndarray, colors: np.ndarray) -> None:
        """The reconstructed surface (base mm) with per-point RGB colours (uint8)."""
        if self.cloud is not None:
            self.cloud.remove()
        self.cloud = self.server.scene.add_point_cloud(
            "/reconstruction", (points_base_mm * MM).astype(np.float32), colors=colors,
            point_size=0.0012, point_shape="rounded", visible=self.shown["cloud"],
        )

    def set_views(self, views: list[tuple[np.ndarray, tuple[int, int, int]]]) -> None:
        """A self-check's surfaces (base mm), each view's in its colour, in place of any earlier ones."""
        self.clear_views()
        self.views = [self.server.scene.add_point_cloud(f"/selfcheck/view_{k}", (points * MM).astype(np.float32),
                                                        colors=colour, point_size=0.0012, point_shape="rounded",
                                                        visible=self.shown["self-check"])
                      for k, (points, colour) in enumerate(views)]

    def clear_views(self) -> None:
        for handle in self.views:
            handle.remove()
        self.views = []

    def set_live_volume(self, points_base_mm: np.ndarray, gray: np.ndarray) -> None:
        """The bright voxels of the volume compounded so far (base mm), in their gray levels."""
        if self.live is not None:
            self.live.remove()
        colors = np.repeat(gray[:, None], 3, axis=1).astype(np.uint8)
        self.live = self.server.scene.add_point_cloud("/live_volume", (points_base_mm * MM).astype(np.float32),
                                                      colors=colors, point_size=0.0008, point_shape="square",
                                                      visible=self.shown["volume"])

    def set_slices(self, edges_base_mm: np.ndarray) -> None:
        """The outlines (N, 2, 3) of the slices the panel shows, where they cut the volume (base mm)."""
        if self.slices is not None:
            self.slices.points = (edges_base_mm * MM).astype(np.float32)
            return
        self.slices = self.server.scene.add_line_segments("/slices", (edges_base_mm * MM).astype(np.float32),
                                                          colors=LABEL_COLOUR, thickness=2.0, thickness_units="screen",
                                                          visible=self.shown["slices"])

    def clear_volume(self) -> None:
        """Remove a volume session's layers: the test object, the live volume, the cloud, the slices
        and a self-check's surfaces."""
        for handle in (self.object, self.live, self.cloud, self.slices):
            if handle is not None:
                handle.remove()
        self.object = self.live = self.cloud = self.slices = None
        self.clear_views()

    def set_cloud_colors(self, colors: np.ndarray) -> None:
        if self.cloud is not None:
            self.cloud.colors = colors


def registered_points(phantom_to_base: np.ndarray, image_to_phantom: np.ndarray,
                      points_image_mm: np.ndarray) -> np.ndarray:
    """Image-frame marker points (mm) mapped through a registration into the base frame."""
    return transform_points(phantom_to_base @ image_to_phantom, points_image_mm)
