//! PLY reading and writing (hand-written; the format is small).
//!
//! Writing: `binary_little_endian 1.0`, vertices as `float x y z` (+ `uchar red green blue`
//! when the mesh has colours), faces as `list uchar int vertex_indices`: the layout MeshLab,
//! Open3D and trimesh read.
//!
//! Reading: `ascii`, `binary_little_endian` and `binary_big_endian`. The `vertex` element needs
//! `x y z` of any scalar type; `red green blue` are used when all three are present (`uchar`
//! taken as is, float types in [0, 1] scaled by 255). The `face` element needs a list
//! `vertex_indices` (or `vertex_index`) of any integer types; polygons with more than 3
//! vertices are fan-triangulated, lists with fewer than 3 are skipped. Other elements and
//! properties are read and ignored. A point cloud (no `face` element) reads as a mesh without
//! faces.

use std::io::{BufRead, BufReader, Read, Write};
use std::path::Path;

use anyhow::{anyhow, bail, Context, Result};

use super::Mesh;

/// Writes `mesh` as a binary little-endian PLY file.
/// The file appears whole or not at all ([`crate::atomic`]).
pub fn write_ply(mesh: &Mesh, path: &Path) -> Result<()> {
    crate::atomic::write_atomic(path, |w| write_ply_to(mesh, w))
        .with_context(|| format!("writing PLY file {}", path.display()))
}

/// Writes `mesh` as binary little-endian PLY to `w`.
///
/// Fails if the colour count differs from the vertex count or a face index is out of range.
pub fn write_ply_to<W: Write + ?Sized>(mesh: &Mesh, w: &mut W) -> Result<()> {
    let nv = mesh.vertices.len();
    if let Some(c) = &mesh.colors {
        if c.len() != nv {
            bail!("mesh has {} colours for {} vertices", c.len(), nv);
        }
    }
    if let Some(f) = mesh
        .faces
        .iter()
        .find(|f| f.iter().any(|&i| i as usize >= nv))
    {
        bail!("face {f:?} refers to a vertex beyond the {nv} vertices");
    }
    if nv > i32::MAX as usize {
        bail!("too many vertices for PLY int indices: {nv}");
    }
    let mut h = String::from("ply\nformat binary_little_endian 1.0\ncomment written by himap\n");
    h.push_str(&format!("element vertex {nv}\n"));
    h.push_str("property float x\nproperty float y\nproperty float z\n");
    if mesh.colors.is_some() {
        h.push_str("property uchar red\nproperty uchar green\nproperty uchar blue\n");
    }
    h.push_str(&format!("element face {}\n", mesh.faces.len()));
    h.push_str("property list uchar int vertex_indices\nend_header\n");
    w.write_all(h.as_bytes())?;
    let stride = if mesh.colors.is_some() { 15 } else { 12 };
    let mut buf = Vec::with_capacity(stride * nv.min(1 << 16));
    for (i, v) in mesh.vertices.iter().enumerate() {
        for x in v {
            buf.extend_from_slice(&x.to_le_bytes());
        }
        if let Some(c) = &mesh.colors {
            buf.extend_from_slice(&c[i]);
        }
        if buf.len() >= 1 << 20 {
            w.write_all(&buf)?;
            buf.clear();
        }
    }
    for f in &mesh.faces {
        buf.push(3);
        for i in f {
            buf.extend_from_slice(&(*i as i32).to_le_bytes());
        }
        if buf.len() >= 1 << 20 {
            w.write_all(&buf)?;
            buf.clear();
        }
    }
    w.write_all(&buf)?;
    Ok(())
}

/// Reads a PLY file (see the module documentation for what is understood).
pub fn read_ply(path: &Path) -> Result<Mesh> {
    let f = std::fs::File::open(path)
        .with_context(|| format!("opening PLY file {}", path.display()))?;
    read_ply_from(BufReader::new(f)).with_context(|| format!("reading PLY file {}", path.display()))
}

#[derive(Clone, Copy, Debug, PartialEq)]
enum Ty {
    I8,
    U8,
    I16,
    U16,
    I32,
    U32,
    F32,
    F64,
}

impl Ty {
    fn parse(s: &str) -> Result<Ty> {
        Ok(match s {
            "char" | "int8" => Ty::I8,
            "uchar" | "uint8" => Ty::U8,
            "short" | "int16" => Ty::I16,
            "ushort" | "uint16" => Ty::U16,
            "int" | "int32" => Ty::I32,
            "uint" | "uint32" => Ty::U32,
            "float" | "float32" => Ty::F32,
            "double" | "float64" => Ty::F64,
            _ => bail!("unknown property type '{s}'"),
        })
    }

    fn size(self) -> usize {
        match self {
            Ty::I8 | Ty::U8 => 1,
            Ty::I16 | Ty::U16 => 2,
            Ty::I32 | Ty::U32 | Ty::F32 => 4,
            Ty::F64 => 8,
        }
    }

    fn is_float(self) -> bool {
        matches!(self, Ty::F32 | Ty::F64)
    }
}

#[derive(Debug)]
enum Prop {
    Scalar { name: String, ty: Ty },
    List { name: String, count: Ty, item: Ty },
}

#[derive(Debug)]
struct Element {
    name: String,
    count: usize,
    props: Vec<Prop>,
}

#[derive(Clone, Copy, Debug, PartialEq)]
enum Format {
    Ascii,
    Le,
    Be,
}

/// The body of a PLY file: a scalar source over binary bytes or ASCII tokens.
enum Body<'a> {
    Bin {
        bytes: &'a [u8],
        pos: usize,
        big: bool,
    },
    Ascii {
        tokens: std::str::SplitAsciiWhitespace<'a>,
    },
}

impl Body<'_> {
    fn scalar(&mut self, ty: Ty) -> Result<f64> {
        match self {
            Body::Bin { bytes, pos, big } => {
                let n = ty.size();
                let Some(b) = bytes.get(*pos..*pos + n) else {
                    bail!("file ends early (binary body truncated at byte {})", *pos);
                };
                *pos += n;
                let mut a = [0u8; 8];
                a[..n].copy_from_slice(b);
                if *big {
                    a[..n].reverse();
                }
                Ok(match ty {
                    Ty::I8 => a[0] as i8 as f64,
                    Ty::U8 => a[0] as f64,
                    Ty::I16 => i16::from_le_bytes([a[0], a[1]]) as f64,
                    Ty::U16 => u16::from_le_bytes([a[0], a[1]]) as f64,
                    Ty::I32 => i32::from_le_bytes([a[0], a[1], a[2], a[3]]) as f64,
                    Ty::U32 => u32::from_le_bytes([a[0], a[1], a[2], a[3]]) as f64,
                    Ty::F32 => f32::from_le_bytes([a[0], a[1], a[2], a[3]]) as f64,
                    Ty::F64 => f64::from_le_bytes(a),
                })
            }
            Body::Ascii { tokens } => {
                let t = tokens
                    .next()
                    .ok_or_else(|| anyhow!("file ends early (ASCII body)"))?;
                let v: f64 = t
                    .parse()
                    .map_err(|_| anyhow!("bad number '{t}' in ASCII body"))?;
                if !ty.is_float() && v.fract() != 0.0 {
                    bail!("integer property has value '{t}'");
                }
                Ok(v)
            }
        }
    }
}

fn parse_header<R: BufRead>(r: &mut R) -> Result<(Format, Vec<Element>)> {
    let mut line = Vec::new();
    let mut next_line = |r: &mut R| -> Result<Option<String>> {
        line.clear();
        if r.read_until(b'\n', &mut line)? == 0 {
            return Ok(None);
        }
        Ok(Some(String::from_utf8_lossy(&line).trim().to_string()))
    };
    if next_line(r)?.as_deref() != Some("ply") {
        bail!("not a PLY file (first line is not 'ply')");
    }
    let mut format = None;
    let mut elements: Vec<Element> = Vec::new();
    loop {
        let Some(l) = next_line(r)? else {
            bail!("header has no 'end_header'");
        };
        let w: Vec<&str> = l.split_whitespace().collect();
        match w.first().copied() {
            None | Some("comment") | Some("obj_info") => {}
            Some("format") => {
                format = Some(match w.get(1).copied() {
                    Some("ascii") => Format::Ascii,
                    Some("binary_little_endian") => Format::Le,
                    Some("binary_big_endian") => Format::Be,
                    other => bail!("unknown PLY format {other:?}"),
                })
            }
            Some("element") => {
                let (Some(name), Some(count)) = (w.get(1), w.get(2)) else {
                    bail!("bad element line '{l}'");
                };
                let count = count
                    .parse()
                    .map_err(|_| anyhow!("bad element count in '{l}'"))?;
                elements.push(Element {
                    name: name.to_string(),
                    count,
                    props: Vec::new(),
                });
            }
            Some("property") => {
                let el = elements
                    .last_mut()
                    .ok_or_else(|| anyhow!("property before any element: '{l}'"))?;
                let prop = if w.get(1) == Some(&"list") {
                    if w.len() != 5 {
                        bail!("bad list property line '{l}'");
                    }
                    Prop::List {
                        name: w[4].to_string(),
                        count: Ty::parse(w[2])?,
                        item: Ty::parse(w[3])?,
                    }
                } else {
                    if w.len() != 3 {
                        bail!("bad property line '{l}'");
                    }
                    Prop::Scalar {
                        name: w[2].to_string(),
                        ty: Ty::parse(w[1])?,
                    }
                };
                el.props.push(prop);
            }
            Some("end_header") => break,
            Some(other) => bail!("unknown header keyword '{other}'"),
        }
    }
    let format = format.ok_or_else(|| anyhow!("header has no 'format' line"))?;
    Ok((format, elements))
}

/// Reads PLY data from `r` (see the module documentation).
pub fn read_ply_from<R: Read>(r: R) -> Result<Mesh> {
    let mut r = BufReader::new(r);
    let (format, elements) = parse_header(&mut r)?;
    let mut rest = Vec::new();
    r.read_to_end(&mut rest)?;
    let mut body = match format {
        Format::Ascii => Body::Ascii {
            tokens: std::str::from_utf8(&rest)
                .map_err(|_| anyhow!("ASCII body is not valid UTF-8"))?
                .split_ascii_whitespace(),
        },
        Format::Le | Format::Be => Body::Bin {
            bytes: &rest,
            pos: 0,
            big: format == Format::Be,
        },
    };
    // Every property of every entry takes at least one byte (binary) or one character (ASCII),
    // so a count the body cannot hold is refused before anything is sized from it.
    for el in &elements {
        if el.count.saturating_mul(el.props.len()) > rest.len() {
            bail!(
                "element '{}' claims {} entries of {} properties, more than the {} bytes after \
                 the header can hold",
                el.name,
                el.count,
                el.props.len(),
                rest.len()
            );
        }
    }
    let mut mesh = Mesh::default();
    let mut seen_vertex = false;
    for el in &elements {
        if el.props.is_empty() && el.name != "vertex" && el.name != "face" {
            continue; // nothing to read, however many entries it claims
        }
        match el.name.as_str() {
            "vertex" => {
                if seen_vertex {
                    bail!("more than one 'vertex' element");
                }
                seen_vertex = true;
                read_vertices(el, &mut body, &mut mesh)?;
            }
            "face" => read_faces(el, &mut body, &mut mesh)?,
            _ => {
                for _ in 0..el.count {
                    for p in &el.props {
                        skip_prop(p, &mut body)?;
                    }
                }
            }
        }
    }
    if !seen_vertex {
        bail!("no 'vertex' element");
    }
    let nv = mesh.vertices.len();
    if let Some(f) = mesh
        .faces
        .iter()
        .find(|f| f.iter().any(|&i| i as usize >= nv))
    {
        bail!("face {f:?} refers to a vertex beyond the {nv} vertices");
    }
    Ok(mesh)
}

fn skip_prop(p: &Prop, body: &mut Body) -> Result<()> {
    match p {
        Prop::Scalar { ty, .. } => {
            body.scalar(*ty)?;
        }
        Prop::List { count, item, .. } => {
            let n = list_len(body.scalar(*count)?)?;
            for _ in 0..n {
                body.scalar(*item)?;
            }
        }
    }
    Ok(())
}

fn list_len(v: f64) -> Result<usize> {
    if v < 0.0 || v.fract() != 0.0 {
        bail!("bad list length {v}");
    }
    Ok(v as usize)
}

fn read_vertices(el: &Element, body: &mut Body, mesh: &mut Mesh) -> Result<()> {
    let find = |n: &str| {
        el.props
            .iter()
            .position(|p| matches!(p, Prop::Scalar { name, .. } if name == n))
    };
    let (Some(ix), Some(iy), Some(iz)) = (find("x"), find("y"), find("z")) else {
        bail!("vertex element lacks scalar x, y or z");
    };
    let rgb = match (find("red"), find("green"), find("blue")) {
        (Some(r), Some(g), Some(b)) => Some([r, g, b]),
        _ => None,
    };
    mesh.vertices.reserve(el.count);
    let mut colors = rgb.map(|_| Vec::with_capacity(el.count));
    let mut vals = vec![0.0f64; el.props.len()];
    for _ in 0..el.count {
        for (k, p) in el.props.iter().enumerate() {
            match p {
                Prop::Scalar { ty, .. } => vals[k] = body.scalar(*ty)?,
                list => skip_prop(list, body)?,
            }
        }
        mesh.vertices
            .push([vals[ix] as f32, vals[iy] as f32, vals[iz] as f32]);
        if let (Some(cols), Some(idx)) = (colors.as_mut(), rgb) {
            let c = idx.map(|k| {
                let float = matches!(el.props[k], Prop::Scalar { ty, .. } if ty.is_float());
                let v = if float { vals[k] * 255.0 } else { vals[k] };
                v.round().clamp(0.0, 255.0) as u8
            });
            cols.push(c);
        }
    }
    mesh.colors = colors;
    Ok(())
}

fn read_faces(el: &Element, body: &mut Body, mesh: &mut Mesh) -> Result<()> {
    let idx = el
        .props
        .iter()
        .position(|p| {
            matches!(p, Prop::List { name, .. } if name == "vertex_indices" || name == "vertex_index")
        })
        .ok_or_else(|| anyhow!("face element lacks a 'vertex_indices' list"))?;
    if let Prop::List { item, .. } = el.props[idx] {
        if item.is_float() {
            bail!("face vertex indices have a float type");
        }
    }
    mesh.faces.reserve(el.count);
    let mut poly: Vec<u32> = Vec::new();
    for _ in 0..el.count {
        for (k, p) in el.props.iter().enumerate() {
            match p {
                Prop::List { count, item, .. } if k == idx => {
                    let n = list_len(body.scalar(*count)?)?;
                    poly.clear();
                    for _ in 0..n {
                        let v = body.scalar(*item)?;
                        if v < 0.0 || v > u32::MAX as f64 {
                            bail!("face vertex index {v} out of range");
                        }
                        poly.push(v as u32);
                    }
                    for i in 1..poly.len().saturating_sub(1) {
                        mesh.faces.push([poly[0], poly[i], poly[i + 1]]);
                    }
                }
                other => skip_prop(other, body)?,
            }
        }
    }
    Ok(())
}
