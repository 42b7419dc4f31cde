"""Render a qsdem snapshot (.vtu, or the last step of a .pvd series) to a PNG with ParaView.

Every particle is drawn as its true ellipsoid: Tensor Glyph of a sphere of radius 1 by the
point array shape_tensor = R diag(a, b, c) R^T, scale factor 1 (docs/visualisation.md).
The periodic cell is drawn from the field array cell_matrix.

    xvfb-run -a pvbatch scripts/render-packing.py INPUT.vtu OUTPUT.png [--color force]

Colour: force (|contact resultant|, N, default), radius (equal-volume radius, m), contacts
(number of touching neighbours) or none. Debian's pvbatch is built for X: run it under
xvfb-run on a machine without a display. Debian packages:
    apt-get install -y --no-install-recommends paraview python3-paraview python3-numpy xvfb xauth
"""
import argparse
import math
import sys

from paraview import servermanager as sm
from paraview.simple import (Calculator, ColorBy, GetColorTransferFunction, GetScalarBar, OpenDataFile,
                             ProgrammableFilter, Render, SaveScreenshot, Show, TensorGlyph,
                             CreateView, SetActiveView)

parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
parser.add_argument("input", help="snapshot .vtu (or series .pvd: its last time step)")
parser.add_argument("output", help="PNG to write")
parser.add_argument("--color", choices=["force", "radius", "contacts", "none"], default="force")
parser.add_argument("--size", default="1200x900", help="image size WxH in pixels (default 1200x900)")
parser.add_argument("--resolution", type=int, default=20,
                    help="sphere facets around (default 20; lower it for very large packings)")
parser.add_argument("--no-cell", action="store_true", help="do not draw the cell box")
args = parser.parse_args(sys.argv[1:])
width, height = (int(v) for v in args.size.lower().split("x"))

reader = OpenDataFile(args.input)
if reader is None:
    sys.exit(f"render-packing: cannot open {args.input}")
times = list(getattr(reader, "TimestepValues", None) or [])
time = times[-1] if times else None
reader.UpdatePipeline(time) if time is not None else reader.UpdatePipeline()
data = sm.Fetch(reader)
if data.IsA("vtkMultiBlockDataSet"):  # a .pvd read as blocks: use the first
    data = data.GetBlock(0)
if data is None or data.GetPointData().GetArray("shape_tensor") is None:
    sys.exit(f"render-packing: {args.input} has no point array 'shape_tensor' (not a qsdem snapshot?)")
n = data.GetNumberOfPoints()

# Colour array: |force| needs a Calculator; the others are point arrays of the file.
source, scalars, title = reader, None, None
if args.color == "force":
    source = Calculator(Input=reader, ResultArrayName="force_magnitude", Function="mag(force)")
    scalars, title = "force_magnitude", "force magnitude (N)"
elif args.color == "radius":
    scalars, title = "radius", "R (m)"
elif args.color == "contacts":
    scalars, title = "contacts", "contacts"

glyph = TensorGlyph(Input=source, GlyphType="Sphere")
glyph.Tensors = ["POINTS", "shape_tensor"]
glyph.ExtractEigenvalues = 1          # scale the unit sphere by the eigenvalues a, b, c ...
glyph.ScaleFactor = 1.0               # ... and nothing else (ParaView's default is data-dependent)
glyph.LimitScalingByEigenvalues = 0
glyph.GlyphType.Radius = 1.0          # the sphere source's default radius is 0.5
glyph.GlyphType.ThetaResolution = args.resolution
glyph.GlyphType.PhiResolution = max(8, args.resolution * 2 // 3)
glyph.ColorGlyphs = 1 if scalars else 0
if scalars:
    glyph.Scalars = ["POINTS", scalars]
    glyph.Colorby = "input scalars"

view = CreateView("RenderView")
SetActiveView(view)
if time is not None:
    view.ViewTime = time
view.ViewSize = [width, height]
view.OrientationAxesVisibility = 1
view.OrientationAxesLabelColor = [0, 0, 0]
view.UseColorPaletteForBackground = 0
view.Background = [1, 1, 1]

display = Show(glyph, view)
display.Specular = 0.3
if scalars:
    ColorBy(display, ("POINTS", scalars))
    lut = GetColorTransferFunction(scalars)
    lut.ApplyPreset("Viridis (matplotlib)", True)
    glyph.UpdatePipeline(time) if time is not None else glyph.UpdatePipeline()
    lo, hi = glyph.PointData[scalars].GetRange()
    if args.color == "force":
        lo = 0.0  # zero force (rattlers) at the bottom of the scale
    lut.RescaleTransferFunction(lo, hi if hi > lo else lo + 1)
    display.SetScalarBarVisibility(view, True)
    bar = GetScalarBar(lut, view)
    bar.Title = title
    bar.ComponentTitle = ""
    bar.TitleColor = bar.LabelColor = [0, 0, 0]
    bar.TitleFontSize = bar.LabelFontSize = 18
    bar.RangeLabelFormat = "%.3g"
else:
    display.ColorArrayName = ["POINTS", ""]  # solid colour
    display.AmbientColor = display.DiffuseColor = [0.75, 0.6, 0.45]

# The cell: corners h {0,1}^3, with h from the field array cell_matrix (VTK column-major: a1,
# a2, a3 in turn). A filter on the reader, so it follows the cell through a time series; the
# same script is the GUI recipe of docs/visualisation.md.
CELL_BOX_SCRIPT = """
from vtkmodules.vtkCommonCore import vtkPoints
from vtkmodules.vtkCommonDataModel import vtkCellArray
inp = self.GetInputDataObject(0, 0)
if inp.IsA("vtkMultiBlockDataSet"):
    inp = inp.GetBlock(0)
h = inp.GetFieldData().GetArray("cell_matrix")
a = [[h.GetComponent(0, 3 * c + r) for r in range(3)] for c in range(3)]
pts, lines = vtkPoints(), vtkCellArray()
for k in range(8):
    f = (k & 1, k >> 1 & 1, k >> 2 & 1)
    pts.InsertNextPoint([f[0] * a[0][i] + f[1] * a[1][i] + f[2] * a[2][i] for i in range(3)])
for k in range(8):
    for bit in (1, 2, 4):
        if not k & bit:
            lines.InsertNextCell(2, [k, k | bit])
out = self.GetPolyDataOutput()
out.SetPoints(pts)
out.SetLines(lines)
"""
if data.GetFieldData().GetArray("cell_matrix") is not None and not args.no_cell:
    box = ProgrammableFilter(Input=reader, OutputDataSetType="vtkPolyData", Script=CELL_BOX_SCRIPT)
    box_display = Show(box, view)
    box_display.AmbientColor = box_display.DiffuseColor = [0.1, 0.1, 0.1]
    box_display.LineWidth = 2.0

# Camera: an oblique view from the front-right, above, at a distance that fits the bounding
# sphere of the particles (0.9: that sphere is generous for a box-shaped scene).
Render(view)  # paraview.simple resets the camera on a view's first render: do it before placing it
b = glyph.GetDataInformation().GetBounds()
centre = [(b[0] + b[1]) / 2, (b[2] + b[3]) / 2, (b[4] + b[5]) / 2]
radius = 0.5 * math.sqrt((b[1] - b[0]) ** 2 + (b[3] - b[2]) ** 2 + (b[5] - b[4]) ** 2)
direction = [1.0, -1.7, 0.9]
norm = math.hypot(*direction)  # not sum(): pvbatch shadows it with a numpy reduction
angle = 30.0
distance = 0.9 * radius / math.sin(math.radians(angle / 2))
view.CameraParallelProjection = 0
view.CameraViewAngle = angle
view.CameraFocalPoint = centre
view.CameraPosition = [centre[i] + distance * direction[i] / norm for i in range(3)]
view.CameraViewUp = [0, 0, 1]
Render(view)
SaveScreenshot(args.output, view, ImageResolution=[width, height], TransparentBackground=0)
print(f"render-packing: {n} particles from {args.input} -> {args.output} ({width}x{height}, colour: {args.color})")
