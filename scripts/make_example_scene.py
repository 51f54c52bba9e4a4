"""Write the example user scene of ``configs/examples/``: a Mitsuba 3 XML file with OBJ/PLY meshes
and an 8-bit PNG texture beside it, as a Mitsuba user would bring one, plus target photos.

    python3 scripts/make_example_scene.py [--out configs/examples/room]

The room: a white floor and ceiling, a red left wall, a green right wall, a back wall with an
8-bit sRGB PNG texture (``textures/wall.png``), a quad area light under the ceiling, and a
blob (``meshes/blob.ply``) on the floor. The integrator is ``$integrator`` (default ``prb``;
the pose run passes ``prb_projective``) and ``$max_depth`` (default 3).

Targets, one per task of Mitsuba's inverse-rendering tutorials, each a render of the file's
scene with *one* quantity changed (the truths are in ``truth.yaml``), written as
``targets/<task>.exr`` (linear), ``.png`` and ``.jpg`` (8-bit sRGB, as a photo):

- ``red``: red wall reflectance (0.7, 0.3, 0.1) instead of 0.5;
- ``texture``: the back wall's texture ``textures/wall_true.png`` instead of ``wall.png``;
- ``light``: area-light radiance 12 instead of 8 (the lamp is in view: an 8-bit target clips it);
- ``pose``: the blob moved by (0.08, 0, -0.05) and turned 15 degrees about y.

Everything is small (about 100 kB) and made here, so the repository ships it.
"""
from __future__ import annotations

import argparse
import math
from pathlib import Path

import numpy as np
import torch

ROOT = Path(__file__).resolve().parents[1]
RESOLUTION = 48
TEXTURE = 16
TASKS = {  # task -> the values that differ from the scene file
    "red": {"red.bsdf.reflectance.value": [0.7, 0.3, 0.1]},
    "texture": {},  # the texture file differs: wall_true.png
    "light": {"light.emitter.radiance.value": [12.0, 12.0, 12.0]},
    "pose": {"blob.translation": [0.08, 0.0, -0.05], "blob.rotation": [15.0]},
}
TARGET_SPP = 1024

QUAD_OBJ = """# unit quad in the xy plane, facing +z, uv in [0, 1]^2
v -1 -1 0
v 1 -1 0
v 1 1 0
v -1 1 0
vt 0 0
vt 1 0
vt 1 1
vt 0 1
vn 0 0 1
f 1/1/1 2/2/1 3/3/1
f 1/1/1 3/3/1 4/4/1
"""

SCENE_XML = """<scene version="3.0.0">
    <default name="integrator" value="prb"/>
    <default name="max_depth" value="3"/>
    <default name="spp" value="4"/>
    <default name="resolution" value="{res}"/>
    <default name="wall_texture" value="textures/wall.png"/>

    <integrator type="$integrator">
        <integer name="max_depth" value="$max_depth"/>
    </integrator>

    <sensor type="perspective">
        <float name="fov" value="40"/>
        <transform name="to_world">
            <lookat origin="0, 0, 3.9" target="0, 0, 0" up="0, 1, 0"/>
        </transform>
        <sampler type="independent"><integer name="sample_count" value="$spp"/></sampler>
        <film type="hdrfilm">
            <integer name="width" value="$resolution"/>
            <integer name="height" value="$resolution"/>
            <rfilter type="box"/>
            <string name="pixel_format" value="rgb"/>
        </film>
    </sensor>

    <bsdf type="diffuse" id="white"><rgb name="reflectance" value="0.75"/></bsdf>

    <shape type="obj" id="floor">
        <string name="filename" value="meshes/quad.obj"/>
        <transform name="to_world"><rotate x="1" angle="-90"/><translate y="-1"/></transform>
        <ref id="white"/>
    </shape>
    <shape type="obj" id="ceiling">
        <string name="filename" value="meshes/quad.obj"/>
        <transform name="to_world"><rotate x="1" angle="90"/><translate y="1"/></transform>
        <ref id="white"/>
    </shape>
    <shape type="obj" id="back">
        <string name="filename" value="meshes/quad.obj"/>
        <transform name="to_world"><translate z="-1"/></transform>
        <bsdf type="diffuse">
            <texture type="bitmap" name="reflectance">
                <string name="filename" value="$wall_texture"/>
                <string name="filter_type" value="nearest"/>
            </texture>
        </bsdf>
    </shape>
    <shape type="obj" id="red">
        <string name="filename" value="meshes/quad.obj"/>
        <transform name="to_world"><rotate y="1" angle="90"/><translate x="-1"/></transform>
        <bsdf type="diffuse"><rgb name="reflectance" value="0.5"/></bsdf>
    </shape>
    <shape type="obj" id="green">
        <string name="filename" value="meshes/quad.obj"/>
        <transform name="to_world"><rotate y="1" angle="-90"/><translate x="1"/></transform>
        <bsdf type="diffuse"><rgb name="reflectance" value="0.15, 0.6, 0.15"/></bsdf>
    </shape>
    <shape type="obj" id="light">
        <string name="filename" value="meshes/quad.obj"/>
        <transform name="to_world"><scale value="0.25"/><rotate x="1" angle="90"/><translate y="0.99"/></transform>
        <emitter type="area"><rgb name="radiance" value="8"/></emitter>
        <bsdf type="diffuse"><rgb name="reflectance" value="0"/></bsdf>
    </shape>
    <shape type="ply" id="blob">
        <string name="filename" value="meshes/blob.ply"/>
        <bsdf type="diffuse"><rgb name="reflectance" value="0.3, 0.3, 0.75"/></bsdf>
    </shape>
</scene>
"""


def blob_mesh(rings: int = 10, segments: int = 16) -> tuple[np.ndarray, np.ndarray]:
    """A lumpy UV sphere (radius ~0.35) on the floor: (V, 3) float32 vertices, (F, 3) int faces.
    Lumpy, so that a rotation about y changes its silhouette."""
    verts = [(0.0, 0.35, 0.0)]
    for i in range(1, rings):
        theta = math.pi * i / rings
        for j in range(segments):
            phi = 2 * math.pi * j / segments
            r = 0.35 * (1.0 + 0.25 * math.cos(3 * phi) * math.sin(theta))
            verts.append((r * math.sin(theta) * math.cos(phi), 0.35 * math.cos(theta), r * math.sin(theta) * math.sin(phi)))
    verts.append((0.0, -0.35, 0.0))
    faces = []
    for j in range(segments):
        faces.append((0, 1 + (j + 1) % segments, 1 + j))
    for i in range(rings - 2):
        a, b = 1 + i * segments, 1 + (i + 1) * segments
        for j in range(segments):
            k = (j + 1) % segments
            faces += [(a + j, a + k, b + j), (a + k, b + k, b + j)]
    last, bottom = 1 + (rings - 2) * segments, len(verts) - 1
    for j in range(segments):
        faces.append((last + j, last + (j + 1) % segments, bottom))
    v = np.asarray(verts, np.float32) + np.array([0.25, -1.0 + 0.35 * 0.75, 0.1], np.float32)
    return v, np.asarray(faces, np.int32)


def write_ply(path: Path, vertices: np.ndarray, faces: np.ndarray) -> None:
    lines = ["ply", "format ascii 1.0", f"element vertex {len(vertices)}", "property float x", "property float y",
             "property float z", f"element face {len(faces)}", "property list uchar int vertex_indices", "end_header"]
    lines += [f"{x:.6f} {y:.6f} {z:.6f}" for x, y, z in vertices]
    lines += [f"3 {a} {b} {c}" for a, b, c in faces]
    path.write_text("\n".join(lines) + "\n")


def wall_texture(seed: int) -> torch.Tensor:
    """A (3, T, T) linear-radiance texture: soft colour blocks, values in [0.05, 0.9]."""
    g = torch.Generator().manual_seed(seed)
    coarse = 0.05 + 0.85 * torch.rand(3, 4, 4, generator=g)
    return torch.nn.functional.interpolate(coarse[None], size=(TEXTURE, TEXTURE), mode="nearest")[0]


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--out", default=str(ROOT / "configs" / "examples" / "room"))
    args = parser.parse_args()
    out = Path(args.out)
    for sub in ("meshes", "textures", "targets"):
        (out / sub).mkdir(parents=True, exist_ok=True)

    import torchir
    from torchir.derived import rigid_transform
    from torchir.functions import render
    from torchir.imageio import write_image

    (out / "meshes" / "quad.obj").write_text(QUAD_OBJ)
    write_ply(out / "meshes" / "blob.ply", *blob_mesh())
    (out / "scene.xml").write_text(SCENE_XML.format(res=RESOLUTION))
    write_image(out / "textures" / "wall.png", wall_texture(seed=1))  # the file's (wrong) texture
    true_texture = wall_texture(seed=2)
    write_image(out / "textures" / "wall_true.png", true_texture)

    lines = []
    for task, values in TASKS.items():
        integrator = "prb_projective" if task == "pose" else "prb"  # only the pose moves edges
        texture = "textures/wall_true.png" if task == "texture" else "textures/wall.png"
        scene = torchir.Scene.from_file(out / "scene.xml", integrator=integrator, wall_texture=texture)
        if task == "pose":
            rigid_transform(scene, "blob", rotation_axis=[0, 1, 0])
        truth = {k: torch.tensor(v, dtype=torch.float32) for k, v in values.items()}
        with torch.no_grad():
            target = render(scene, truth, spp=TARGET_SPP, seed=7)
        for suffix in ("exr", "png", "jpg"):
            write_image(out / "targets" / f"{task}.{suffix}", target)
        lines += [f"  {k}: {v}" for k, v in values.items()]
        if task == "texture":
            lines.append("  back.bsdf.reflectance.data: textures/wall_true.png")
    (out / "truth.yaml").write_text("# true values behind targets/<task>.*; everything else is as in scene.xml\n"
                                    "truth:\n" + "\n".join(lines) + "\n")
    print(f"wrote {out} ({sum(f.stat().st_size for f in out.rglob('*') if f.is_file()) / 1024:.0f} kB)")


if __name__ == "__main__":
    main()
