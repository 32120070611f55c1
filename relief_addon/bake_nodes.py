"""Baked BSDF -> packed float32 lookup image + reusable shader node group (bpy only here).

The physics (what the rows mean, why they are indexed by the view angle, how weights
account for the closures' own albedo) is in the backend: `relief_bsdf.bake`.  This module
only builds Blender data:

- image "Relief LUT: <name>": C x (2 * 5) float32 RGBA, non-colour data, packed, fake user;
- node group "Relief LUT coordinate": (Row) -> texel-centred (u, v) from the view angle
  theta_v = acos(|I . N|) and Backfacing (selects the inside row block);
- node group "Relief LUT BSDF: <name>": four Cycles closures whose colours and roughnesses are
  read from the image (Linear interpolation, EXTEND), summed into one BSDF output
  (anisotropic reflection lobe when the table is; as Cycles has no anisotropic rough
  transmission, an anisotropic transmitted lobe is an isotropic Refraction closure whose normal
  a random facet slope tilts per shading point: `_tilted_normal`, relief_bsdf.bake);
- node group "Relief BSDF: <name>": what a user drops into a material, with inputs Tint,
  Haze, Fitted (fitted / measured-as-is table) and Rotation (`build_node_group`).
Re-baking updates images and groups in place; baking onto an object adds a material slot, given
to every face of a mesh, or to the rough face of a plate the add-on made (`assign_to_rough_face`).
"""
from __future__ import annotations

import math
from pathlib import Path

import bpy
import numpy as np

GROUP_PREFIX = "Relief BSDF: "
LUT_GROUP_PREFIX = "Relief LUT BSDF: "
IMAGE_PREFIX = "Relief LUT: "
COORD_GROUP = "Relief LUT coordinate"
CALIBRATION = Path(__file__).resolve().parent / "data" / "cycles_albedo.npz"


def closure_albedo():
    """The measured Cycles closure albedo shipped with the add-on (None if missing)."""
    from relief_bsdf.bake import ClosureAlbedo
    return ClosureAlbedo.load(CALIBRATION) if CALIBRATION.exists() else None


def lut_image(lut) -> bpy.types.Image:
    """Packed float32 data image holding the LUT rows (row 0 at the bottom); an image of the
    same name is updated in place (same datablock, so every user of it sees the new rows)."""
    name = IMAGE_PREFIX + lut.name
    n_cols, n_rows = lut.rows.shape[1], lut.rows.shape[0]
    img = bpy.data.images.get(name)
    if img is not None and tuple(img.size) != (n_cols, n_rows):
        img.scale(n_cols, n_rows)
    if img is None:
        img = bpy.data.images.new(name, n_cols, n_rows, alpha=True, float_buffer=True, is_data=True)
    img.colorspace_settings.is_data = True
    img.pixels.foreach_set(lut.image_pixels())
    img.pack()
    img.use_fake_user = True
    img["relief_theta_deg"] = [float(lut.theta_deg[0]), float(lut.theta_deg[-1])]
    return img


def _group(name: str, sockets: list[tuple[str, str, str]]) -> bpy.types.ShaderNodeTree:
    """The node group `name`, emptied of nodes, with (name, in_out, socket_type) sockets.

    An existing group is reused (its datablock, hence every material and group node using it,
    stays), and its interface sockets are kept where they already match, so links to them in
    the user's materials survive a re-bake."""
    g = bpy.data.node_groups.get(name) or bpy.data.node_groups.new(name, "ShaderNodeTree")
    g.nodes.clear()
    have = {(it.name, it.in_out): it for it in g.interface.items_tree if getattr(it, "item_type", "") == "SOCKET"}
    for (sname, io), it in have.items():
        if (sname, io, it.socket_type) not in sockets:
            g.interface.remove(it)
    for sname, io, stype in sockets:
        it = have.get((sname, io))
        if it is None or it.socket_type != stype:
            g.interface.new_socket(sname, in_out=io, socket_type=stype)
    g.use_fake_user = True
    return g


def _math(nt, op, a=None, b=None, location=(0, 0), label=None):
    n = nt.nodes.new("ShaderNodeMath")
    n.operation = op
    n.location = location
    if label:
        n.label = label
    for k, v in enumerate((a, b)):
        if v is None:
            continue
        if isinstance(v, (int, float)):
            n.inputs[k].default_value = float(v)
        else:
            nt.links.new(v, n.inputs[k])
    return n


def coordinate_group(n_cols: int, n_rows: int, rows_per_side: int) -> bpy.types.ShaderNodeTree:
    """(Row) -> Vector (u, v, 0): u from theta_v (texel centres), v = row (+ block if backfacing)."""
    name = f"{COORD_GROUP} {n_cols}x{n_rows}"
    g = bpy.data.node_groups.get(name)
    if g is not None:
        return g
    g = bpy.data.node_groups.new(name, "ShaderNodeTree")
    g.interface.new_socket("Row", in_out="INPUT", socket_type="NodeSocketFloat")
    g.interface.new_socket("Vector", in_out="OUTPUT", socket_type="NodeSocketVector")
    gi = g.nodes.new("NodeGroupInput")
    gi.location = (-900, 0)
    go = g.nodes.new("NodeGroupOutput")
    go.location = (500, 0)
    geo = g.nodes.new("ShaderNodeNewGeometry")
    geo.location = (-900, -250)
    dot = g.nodes.new("ShaderNodeVectorMath")
    dot.operation = "DOT_PRODUCT"
    dot.location = (-700, -250)
    g.links.new(geo.outputs["Incoming"], dot.inputs[0])
    g.links.new(geo.outputs["Normal"], dot.inputs[1])
    ab = _math(g, "ABSOLUTE", dot.outputs["Value"], location=(-520, -250))
    cl = _math(g, "MINIMUM", ab.outputs[0], 1.0, location=(-360, -250))
    ac = _math(g, "ARCCOSINE", cl.outputs[0], location=(-200, -250), label="theta_v (rad)")
    # u = theta / (pi/2) * (C - 1) / C + 0.5 / C
    su = _math(g, "MULTIPLY", ac.outputs[0], (2.0 / math.pi) * (n_cols - 1) / n_cols, location=(-40, -250))
    u = _math(g, "ADD", su.outputs[0], 0.5 / n_cols, location=(120, -250), label="u")
    # v = (row + rows_per_side * backfacing + 0.5) / n_rows
    blk = _math(g, "MULTIPLY", geo.outputs["Backfacing"], float(rows_per_side), location=(-520, 50))
    rr = _math(g, "ADD", gi.outputs["Row"], blk.outputs[0], location=(-360, 50))
    rh = _math(g, "ADD", rr.outputs[0], 0.5, location=(-200, 50))
    v = _math(g, "DIVIDE", rh.outputs[0], float(n_rows), location=(-40, 50), label="v")
    comb = g.nodes.new("ShaderNodeCombineXYZ")
    comb.location = (300, 0)
    g.links.new(u.outputs[0], comb.inputs["X"])
    g.links.new(v.outputs[0], comb.inputs["Y"])
    g.links.new(comb.outputs[0], go.inputs["Vector"])
    return g


def _lut_tex(g, img, coord, row: int, location):
    cg = g.nodes.new("ShaderNodeGroup")
    cg.node_tree = coord
    cg.inputs["Row"].default_value = float(row)
    cg.location = (location[0] - 220, location[1])
    tex = g.nodes.new("ShaderNodeTexImage")
    tex.image = img
    tex.interpolation = "Linear"
    tex.extension = "EXTEND"
    tex.location = location
    tex.label = f"row {row}"
    g.links.new(cg.outputs["Vector"], tex.inputs["Vector"])
    return tex


def _metallic_lobe(g, lut, tex, roughness_socket, geo, loc, aniso=None):
    """Fresnel-weighted GGX reflection lobe: Metallic BSDF (physical conductor, extinction 0,
    IOR n per channel, 1/n when back-facing) times the LUT's green weight (two halves through
    Mix Shader factors, which Cycles clamps to [0, 1], so weights up to 2 pass)."""
    b = g.nodes.new("ShaderNodeBsdfMetallic")
    b.location = loc
    b.label = "diffuse_R"
    b.fresnel_type = "PHYSICAL_CONDUCTOR"
    b.distribution = "GGX"
    b.inputs["Extinction"].default_value = (0.0, 0.0, 0.0)
    g.links.new(roughness_socket, b.inputs["Roughness"])
    if aniso is not None:
        _anisotropic(g, b, *aniso)
    mix = g.nodes.new("ShaderNodeMix")
    mix.data_type = "VECTOR"
    mix.location = (loc[0] - 200, loc[1] - 150)
    vec_in = [s for s in mix.inputs if s.name == "A" and s.type == "VECTOR"]
    vec_b = [s for s in mix.inputs if s.name == "B" and s.type == "VECTOR"]
    vec_out = [s for s in mix.outputs if s.type == "VECTOR"][0]
    vec_in[0].default_value = lut.ior_rgb
    vec_b[0].default_value = tuple(1.0 / n for n in lut.ior_rgb)
    g.links.new(geo.outputs["Backfacing"], mix.inputs["Factor"])
    g.links.new(vec_out, b.inputs["IOR"])
    sc = g.nodes.new("ShaderNodeSeparateColor")
    sc.location = (loc[0] - 200, loc[1] + 100)
    g.links.new(tex.outputs["Color"], sc.inputs["Color"])
    half = _math(g, "MULTIPLY", sc.outputs["Green"], 0.5, location=(loc[0] - 20, loc[1] + 100))
    add = g.nodes.new("ShaderNodeAddShader")
    add.location = (loc[0] + 300, loc[1])
    for k in range(2):
        m = g.nodes.new("ShaderNodeMixShader")
        m.location = (loc[0] + 150, loc[1] - 60 * k)
        g.links.new(half.outputs[0], m.inputs["Fac"])
        g.links.new(b.outputs[0], m.inputs[2])
        g.links.new(m.outputs[0], add.inputs[k])
    return add


def _anisotropic(g, bsdf, anisotropy_socket, tangent_socket, rotation_socket) -> None:
    g.links.new(anisotropy_socket, bsdf.inputs["Anisotropy"])
    g.links.new(tangent_socket, bsdf.inputs["Tangent"])
    g.links.new(rotation_socket, bsdf.inputs["Rotation"])


def _relief_x_tangent(g, location):
    """World-space direction of the object's +x axis: the relief's x (mesh_import lays the map's
    columns along object x), the tangent of the anisotropic lobe."""
    vt = g.nodes.new("ShaderNodeVectorTransform")
    vt.vector_type, vt.convert_from, vt.convert_to = "VECTOR", "OBJECT", "WORLD"
    vt.inputs["Vector"].default_value = (1.0, 0.0, 0.0)
    vt.location = location
    vt.label = "relief x (tangent)"
    return vt.outputs["Vector"]


def _vmath(g, op, a, b=None, location=(0, 0)):
    n = g.nodes.new("ShaderNodeVectorMath")
    n.operation = op
    n.location = location
    g.links.new(a, n.inputs[0])
    if b is not None:
        g.links.new(b, n.inputs[1 if op != "SCALE" else "Scale"])
    return n.outputs["Value" if op == "DOT_PRODUCT" else "Vector"]


def _tilted_normal(g, tilt_tex, geo, tangent, rotation_socket, loc):
    """Normal of one random facet per shading point for the stretched transmitted lobe
    (relief_bsdf.bake.transmission_tilt): m = normalize(N - s t), t the relief's x axis turned
    about N by Rotation (a quarter more where c_T < 0) and made perpendicular to N,
    s = |c_T| (2u - 1) / (2 sqrt(u (1 - u))) (`tilt_slope`), u from a White Noise texture of the
    position, so every path sample sees another facet."""
    x, y = loc
    sep = g.nodes.new("ShaderNodeSeparateColor")
    sep.location = (x - 900, y)
    g.links.new(tilt_tex.outputs["Color"], sep.inputs["Color"])
    c = _math(g, "ABSOLUTE", sep.outputs["Red"], location=(x - 700, y), label="tilt scale c_T")
    quarter = _math(g, "MULTIPLY", _math(g, "LESS_THAN", sep.outputs["Red"], 0.0, location=(x - 700, y - 150)).outputs[0],
                    0.5 * math.pi, location=(x - 550, y - 150))
    turn = _math(g, "MULTIPLY", rotation_socket, 2.0 * math.pi, location=(x - 550, y - 300))
    angle = _math(g, "ADD", quarter.outputs[0], turn.outputs[0], location=(x - 400, y - 200), label="tilt azimuth")
    rot = g.nodes.new("ShaderNodeVectorRotate")
    rot.rotation_type = "AXIS_ANGLE"
    rot.invert = True      # the closures' Rotation turns the other way round N than this node (measured)
    rot.location = (x - 250, y - 250)
    g.links.new(tangent, rot.inputs["Vector"])
    g.links.new(geo.outputs["Normal"], rot.inputs["Axis"])
    g.links.new(angle.outputs[0], rot.inputs["Angle"])
    along = _vmath(g, "DOT_PRODUCT", rot.outputs["Vector"], geo.outputs["Normal"], (x - 100, y - 400))
    perp = _vmath(g, "SUBTRACT", rot.outputs["Vector"],
                  _vmath(g, "SCALE", geo.outputs["Normal"], along, (x - 100, y - 250)), (x + 50, y - 250))
    noise = g.nodes.new("ShaderNodeTexWhiteNoise")
    noise.noise_dimensions = "3D"
    noise.location = (x - 700, y + 250)
    g.links.new(geo.outputs["Position"], noise.inputs["Vector"])
    u = _math(g, "MAXIMUM", _math(g, "MINIMUM", noise.outputs["Value"], 1.0 - 1e-6,
                                  location=(x - 550, y + 250)).outputs[0], 1e-6, location=(x - 400, y + 250))
    num = _math(g, "SUBTRACT", _math(g, "MULTIPLY", u.outputs[0], 2.0, location=(x - 250, y + 350)).outputs[0], 1.0,
                location=(x - 100, y + 350))
    one_minus = _math(g, "SUBTRACT", 1.0, u.outputs[0], location=(x - 250, y + 200))
    root = _math(g, "SQRT", _math(g, "MULTIPLY", u.outputs[0], one_minus.outputs[0], location=(x - 100, y + 200)).outputs[0],
                 location=(x + 50, y + 200))
    t = _math(g, "DIVIDE", num.outputs[0], _math(g, "MULTIPLY", root.outputs[0], 2.0, location=(x + 200, y + 200)).outputs[0],
              location=(x + 350, y + 300))
    slope = _math(g, "MULTIPLY", t.outputs[0], c.outputs[0], location=(x + 500, y + 300), label="facet slope")
    m = _vmath(g, "SUBTRACT", geo.outputs["Normal"], _vmath(g, "SCALE", perp, slope.outputs[0], (x + 650, y)),
               (x + 800, y))
    return _vmath(g, "NORMALIZE", m, location=(x + 950, y))


def _tinted(g, colour_socket, tint_socket, location):
    m = g.nodes.new("ShaderNodeMix")
    m.data_type, m.blend_type = "RGBA", "MULTIPLY"
    m.location = location
    m.inputs["Factor"].default_value = 1.0
    g.links.new(colour_socket, m.inputs[6])          # A (colour)
    g.links.new(tint_socket, m.inputs[7])            # B (colour)
    return m.outputs[2]                              # Result (colour)


def build_lut_group(lut, img: bpy.types.Image | None = None) -> bpy.types.ShaderNodeTree:
    """The closures of one baked table: group "Relief LUT BSDF: <name>" (inputs Tint, Rotation).

    Four Cycles closures whose colours and roughnesses are read from the LUT image; the
    reflection lobe is anisotropic when the table is (Anisotropy from the roughness row's third
    channel, tangent = the object's x axis, turned by Rotation: 0.25 = 90 deg).  The two
    transmission closures are Refraction BSDFs, isotropic in Cycles whatever their inputs (no
    Cycles closure transmits anisotropically: Refraction and Glass have no anisotropy,
    Principled's reaches its specular layer only, OSL's microfacet refraction drops alpha_y); for
    an anisotropic table the rough one gets the narrow width and a randomly tilted normal
    (`_tilted_normal`, the same tangent and Rotation), which stretches the rendered lobe along
    the wide axis.  Tint multiplies the transmitted closures (a coloured plate)."""
    from relief_bsdf.bake import ROW_NAMES, ROWS_PER_SIDE
    img = img or lut_image(lut)
    n_cols, n_rows = lut.rows.shape[1], lut.rows.shape[0]
    coord = coordinate_group(n_cols, n_rows, ROWS_PER_SIDE)
    g = _group(LUT_GROUP_PREFIX + lut.name, [("Tint", "INPUT", "NodeSocketColor"),
                                             ("Rotation", "INPUT", "NodeSocketFloat"),
                                             ("BSDF", "OUTPUT", "NodeSocketShader")])
    gi = g.nodes.new("NodeGroupInput")
    gi.location = (-700, -1300)
    go = g.nodes.new("NodeGroupOutput")
    go.location = (900, 0)
    tex = {r: _lut_tex(g, img, coord, k, (-300, 300 - 260 * k)) for k, r in enumerate(ROW_NAMES)}
    sep = g.nodes.new("ShaderNodeSeparateColor")
    sep.location = (-20, -1000)
    g.links.new(tex["roughness"].outputs["Color"], sep.inputs["Color"])
    geo = g.nodes.new("ShaderNodeNewGeometry")
    geo.location = (-20, -1250)
    # signed anisotropy (relief_bsdf.bake.closure_anisotropy): |value|, and a quarter turn where negative
    a_abs = _math(g, "ABSOLUTE", sep.outputs["Blue"], location=(150, -1400), label="anisotropy")
    neg = _math(g, "LESS_THAN", sep.outputs["Blue"], 0.0, location=(150, -1550))
    quarter = _math(g, "MULTIPLY", neg.outputs[0], 0.25, location=(300, -1550))
    rot = _math(g, "ADD", quarter.outputs[0], gi.outputs["Rotation"], location=(450, -1550), label="rotation")
    tangent = _relief_x_tangent(g, (-300, -1500))
    aniso = (a_abs.outputs[0], tangent, rot.outputs[0])
    closures = []
    spec = [("specular_R", "ShaderNodeBsdfGlossy", None), ("diffuse_R", None, "Red"),
            ("specular_T", "ShaderNodeBsdfRefraction", None), ("diffuse_T", "ShaderNodeBsdfRefraction", "Green")]
    for k, (row, kind, rough) in enumerate(spec):
        loc = (250, 400 - 280 * k)
        if row == "diffuse_R" and lut.reflection_closure == "metallic":
            closures.append(_metallic_lobe(g, lut, tex[row], sep.outputs[rough], geo, loc, aniso))
            continue
        b = g.nodes.new(kind or "ShaderNodeBsdfGlossy")
        b.location = loc
        b.label = row
        b.distribution = "GGX"
        colour = tex[row].outputs["Color"]
        if b.bl_idname == "ShaderNodeBsdfRefraction":
            b.inputs["IOR"].default_value = lut.ior
            colour = _tinted(g, colour, gi.outputs["Tint"], (loc[0] - 150, loc[1] - 120))
            if row == "diffuse_T" and lut.transmission_tilt > 0:
                g.links.new(_tilted_normal(g, tex["transmission_tilt"], geo, tangent, gi.outputs["Rotation"],
                                           (loc[0] - 1200, loc[1] - 2200)), b.inputs["Normal"])
        else:
            b.distribution = "MULTI_GGX"
            if row == "diffuse_R":
                _anisotropic(g, b, *aniso)
        g.links.new(colour, b.inputs["Color"])
        if rough is None:
            b.inputs["Roughness"].default_value = 0.0
        else:
            g.links.new(sep.outputs[rough], b.inputs["Roughness"])
        closures.append(b)
    acc = closures[0].outputs[0]
    for k, b in enumerate(closures[1:]):
        add = g.nodes.new("ShaderNodeAddShader")
        add.location = (550, 300 - 200 * k)
        g.links.new(acc, add.inputs[0])
        g.links.new(b.outputs[0], add.inputs[1])
        acc = add.outputs[0]
    g.links.new(acc, go.inputs["BSDF"])
    g["relief_image"] = img.name
    g["relief_anisotropy"] = float(lut.anisotropy)
    return g


def _set_default(g, name: str, value, lo=None, hi=None) -> None:
    it = next(i for i in g.interface.items_tree if getattr(i, "name", "") == name and i.in_out == "INPUT")
    it.default_value = value
    if lo is not None:
        it.min_value, it.max_value = lo, hi


def build_node_group(lut, img: bpy.types.Image | None = None, fitted=None, name: str | None = None,
                     table: str = "") -> bpy.types.ShaderNodeTree:
    """The user-facing node group "Relief BSDF: <name>" (default name: the LUT's).

    Inputs: Tint (colour of the transmitted light), Haze (0 = smooth glass of the same index,
    1 = the relief as baked; in between a mix of the two, energy-conserving as both are),
    Fitted (1 = the fitted table `fitted`, 0 = the relief measured as is `lut`; without a
    fitted table both are the measured one), Rotation (turns the anisotropic lobe's tangent,
    the relief's x axis, about the normal; 0.25 = 90 deg).  Output: BSDF.  Re-baking updates
    the group in place (`_group`): materials using it keep it.  `table`: the table file, kept
    in the group (`relief_table`) so a re-bake of the same file finds this group.
    """
    img = img or lut_image(lut)
    measured = build_lut_group(lut, img)
    fit_group = build_lut_group(fitted) if fitted is not None else measured
    g = _group(GROUP_PREFIX + (name or lut.name), [("Tint", "INPUT", "NodeSocketColor"),
                                                   ("Haze", "INPUT", "NodeSocketFloat"),
                                                   ("Fitted", "INPUT", "NodeSocketFloat"),
                                                   ("Rotation", "INPUT", "NodeSocketFloat"),
                                                   ("BSDF", "OUTPUT", "NodeSocketShader")])
    _set_default(g, "Tint", (1.0, 1.0, 1.0, 1.0))
    _set_default(g, "Haze", 1.0, 0.0, 1.0)
    _set_default(g, "Fitted", 1.0 if fitted is not None else 0.0, 0.0, 1.0)
    _set_default(g, "Rotation", 0.0)
    gi = g.nodes.new("NodeGroupInput")
    gi.location = (-600, 0)
    go = g.nodes.new("NodeGroupOutput")
    go.location = (600, 0)
    nodes = []
    for k, sub in enumerate((measured, fit_group)):
        n = g.nodes.new("ShaderNodeGroup")
        n.node_tree = sub
        n.location = (-300, 200 - 250 * k)
        n.label = ("measured", "fitted")[k]
        g.links.new(gi.outputs["Tint"], n.inputs["Tint"])
        g.links.new(gi.outputs["Rotation"], n.inputs["Rotation"])
        nodes.append(n)
    pick = g.nodes.new("ShaderNodeMixShader")
    pick.location = (0, 100)
    pick.label = "fitted / measured"
    g.links.new(gi.outputs["Fitted"], pick.inputs["Fac"])
    g.links.new(nodes[0].outputs["BSDF"], pick.inputs[1])
    g.links.new(nodes[1].outputs["BSDF"], pick.inputs[2])
    smooth = g.nodes.new("ShaderNodeBsdfGlass")
    smooth.location = (0, -250)
    smooth.label = "smooth boundary"
    smooth.distribution = "GGX"
    smooth.inputs["Roughness"].default_value = 0.0
    smooth.inputs["IOR"].default_value = float(lut.ior)
    g.links.new(gi.outputs["Tint"], smooth.inputs["Color"])
    haze = g.nodes.new("ShaderNodeMixShader")
    haze.location = (300, 0)
    haze.label = "haze"
    g.links.new(gi.outputs["Haze"], haze.inputs["Fac"])
    g.links.new(smooth.outputs[0], haze.inputs[1])
    g.links.new(pick.outputs[0], haze.inputs[2])
    g.links.new(haze.outputs[0], go.inputs["BSDF"])
    g["relief_ior"] = float(lut.ior)
    g["relief_rgb_nm"] = list(lut.rgb_nm)
    g["relief_image"] = img.name
    g["relief_reflection_closure"] = lut.reflection_closure
    g["relief_closure_albedo"] = str(lut.info.get("closure_albedo", ""))
    g["relief_haze"] = float(lut.haze)
    g["relief_anisotropy"] = float(lut.anisotropy)
    g["relief_transmission"] = str(lut.info.get("transmission", ""))
    g["relief_transmission_tilt"] = float(lut.transmission_tilt)
    g["relief_fitted"] = fitted is not None
    if table:
        g["relief_table"] = str(table)
    return g


def group_for_table(table: str) -> bpy.types.ShaderNodeTree | None:
    """The node group baked from this table file before, if any (`relief_table`)."""
    for g in bpy.data.node_groups:
        if g.name.startswith(GROUP_PREFIX) and g.get("relief_table") == str(table):
            return g
    return None


def has_metallic_bsdf() -> bool:
    """Blender 4.3+ has the Metallic BSDF (physical conductor Fresnel)."""
    return bpy.app.version >= (4, 3, 0)


def bake_tables(tables, name: str, albedo="calibrated"):
    """BsdfTables -> (BakedLut, image, node group)."""
    from relief_bsdf.bake import bake_lut
    alb = closure_albedo() if albedo == "calibrated" else albedo
    closure = "metallic" if has_metallic_bsdf() and (alb is None or getattr(alb, "metallic", 1) is not None) \
        else "glossy"
    lut = bake_lut(tables, name, albedo=alb, reflection_closure=closure)
    img = lut_image(lut)
    return lut, img, build_node_group(lut, img)


def material_for_group(group: bpy.types.ShaderNodeTree, name: str | None = None) -> bpy.types.Material:
    """A material whose surface is the node group (one per group, reused: a material that
    already uses the group is left as the user edited it)."""
    name = name or group.name
    mat = bpy.data.materials.get(name)
    if mat is not None and any(n.bl_idname == "ShaderNodeGroup" and n.node_tree == group for n in mat.node_tree.nodes):
        return mat
    mat = mat or bpy.data.materials.new(name)
    nt = mat.node_tree
    nt.nodes.clear()
    node = nt.nodes.new("ShaderNodeGroup")
    node.node_tree = group
    out = nt.nodes.new("ShaderNodeOutputMaterial")
    out.location = (300, 0)
    nt.links.new(node.outputs["BSDF"], out.inputs["Surface"])
    return mat


def glass_material(ior: float, name: str = "Relief smooth glass") -> bpy.types.Material:
    mat = bpy.data.materials.get(name) or bpy.data.materials.new(name)
    nt = mat.node_tree
    nt.nodes.clear()
    b = nt.nodes.new("ShaderNodeBsdfGlass")
    b.distribution = "MULTI_GGX" if "MULTI_GGX" in [e.identifier for e in b.bl_rna.properties["distribution"].enum_items] \
        else b.distribution
    b.inputs["Roughness"].default_value = 0.0
    b.inputs["IOR"].default_value = float(ior)
    b.inputs["Color"].default_value = (1, 1, 1, 1)
    out = nt.nodes.new("ShaderNodeOutputMaterial")
    nt.links.new(b.outputs[0], out.inputs["Surface"])
    return mat


FACES_WORDS = {
    "all": "every face: the relief's frame on each face is that face's shading normal (z, toward the "
           "side it faces: outside rows) and the object's x axis projected onto the face (x, for an "
           "anisotropic lobe); a sphere, a lens, any closed mesh with outward normals",
    "front": "the plate's rough face, the faces looking along +z (object space); the others smooth glass",
    "back": "the plate's rough face, the faces looking along -z (object space); the others smooth glass",
}


def relief_faces(obj: bpy.types.Object) -> str:
    """Which faces of `obj` carry the baked relief: its rough face ("front" / "back") for a plate the
    add-on made (the object's `relief_rough_face`), else "all" (any other mesh: the relief covers it)."""
    face = obj.get("relief_rough_face")
    return face if face in ("front", "back") else "all"


def assign_to_rough_face(obj: bpy.types.Object, group: bpy.types.ShaderNodeTree, rough_face: str = "front") -> int:
    """Put the baked BSDF on the faces `rough_face` of `obj` (FACES_WORDS); returns its material slot index.

    The node group looks its rows up in each shading point's own frame (the view angle from the
    shading normal, the inside rows where the ray meets the back of a face: `coordinate_group`),
    so one material serves every face of any mesh whose normals point out of the medium:
    "all" gives it to every face.  "front" / "back" (a plate: the relief on one face) give it to the
    faces whose normal is most along +z / -z in object space, the others smooth glass of the
    table's index.  Existing material slots are kept: the material of the group is added as a new
    slot (or its slot reused on a re-bake); an object with no material gets the smooth glass on
    the faces the relief does not cover first.
    """
    if rough_face not in FACES_WORDS:
        raise ValueError(f"rough_face must be one of {sorted(FACES_WORDS)}, got {rough_face!r}")
    me = obj.data
    baked = material_for_group(group)
    if len(me.materials) == 0 and rough_face != "all":
        me.materials.append(glass_material(group.get("relief_ior", 1.5)))
    names = [m.name if m is not None else None for m in me.materials]
    if baked.name in names:
        slot = names.index(baked.name)
    else:
        me.materials.append(baked)
        slot = len(me.materials) - 1
    n = len(me.polygons)
    normals = np.empty(3 * n, np.float32)
    me.polygons.foreach_get("normal", normals)
    nz = normals.reshape(n, 3)[:, 2]
    target = np.ones(n, bool) if rough_face == "all" else (nz > 0.5 if rough_face == "front" else nz < -0.5)
    idx = np.empty(n, np.int32)
    me.polygons.foreach_get("material_index", idx)
    idx[target] = slot
    me.polygons.foreach_set("material_index", idx)
    me.update()
    obj["relief_baked_faces"] = rough_face
    return slot
