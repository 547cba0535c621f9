//! `map.safetensors`: `params.<group>`, `adam_m.<group>`, `adam_v.<group>` (f32) and the
//! metadata `himap_config` (the run's TOML), `himap_aabb` (JSON `[[min], [max]]`) and `adam_t`;
//! [`load_map`] rebuilds the field from it alone.

#[allow(unused_imports)]
use super::*;

/// Writes the map: parameters, Adam moments, configuration and box.
pub fn save_map(path: &Path, config: &Config, data: &ModelData) -> anyhow::Result<()> {
    save_map_with(path, config, data, &[])
}

/// [`save_map`] with more metadata entries (a checkpoint's run state).
pub fn save_map_with(
    path: &Path,
    config: &Config,
    data: &ModelData,
    extra: &[(&str, String)],
) -> anyhow::Result<()> {
    use safetensors::tensor::{Dtype, TensorView};
    let mut bufs: Vec<(String, Vec<u8>, usize)> = Vec::new();
    for g in Group::ALL {
        let i = g as usize;
        for (prefix, v) in [
            ("params", &data.params[i]),
            ("adam_m", &data.m[i]),
            ("adam_v", &data.v[i]),
        ] {
            let bytes: Vec<u8> = v.iter().flat_map(|x| x.to_le_bytes()).collect();
            bufs.push((format!("{prefix}.{}", g.name()), bytes, v.len()));
        }
    }
    let views = bufs
        .iter()
        .map(|(n, b, len)| Ok((n.clone(), TensorView::new(Dtype::F32, vec![*len], b)?)))
        .collect::<Result<Vec<_>, safetensors::SafeTensorError>>()?;
    let aabb = data.layout.config.aabb;
    let mut meta = HashMap::new();
    meta.insert("himap_config".to_string(), config.to_toml());
    meta.insert(
        "himap_aabb".to_string(),
        serde_json::to_string(&[aabb.min, aabb.max])?,
    );
    meta.insert("adam_t".to_string(), data.t.to_string());
    for (k, v) in extra {
        meta.insert(k.to_string(), v.clone());
    }
    let bytes = safetensors::serialize(views, Some(meta))
        .with_context(|| format!("serialising {}", path.display()))?;
    crate::atomic::write_bytes_atomic(path, &bytes)
}

/// Reads a map written by [`save_map`]: its configuration and model data.
pub fn load_map(path: &Path) -> anyhow::Result<(Config, ModelData)> {
    let (config, data, _) = load_map_with_meta(path)?;
    Ok((config, data))
}

/// [`load_map`] and every metadata entry of the file.
pub fn load_map_with_meta(
    path: &Path,
) -> anyhow::Result<(Config, ModelData, HashMap<String, String>)> {
    let bytes = std::fs::read(path).with_context(|| format!("reading {}", path.display()))?;
    load_map_bytes(&bytes).with_context(|| format!("loading map {}", path.display()))
}

/// [`load_map_with_meta`] of a file already read. The configuration in the file sizes the
/// map; it is checked against the file's length before the map is allocated.
pub fn load_map_bytes(
    bytes: &[u8],
) -> anyhow::Result<(Config, ModelData, HashMap<String, String>)> {
    let (_, header) =
        safetensors::SafeTensors::read_metadata(bytes).context("not a safetensors file")?;
    let meta = header.metadata().clone().context("no himap metadata")?;
    let get = |k: &str| {
        meta.get(k)
            .with_context(|| format!("metadata '{k}' missing"))
    };
    let config = Config::from_toml(get("himap_config")?)?;
    let [min, max]: [[f32; 3]; 2] = serde_json::from_str(get("himap_aabb")?)?;
    let t: u32 = get("adam_t")?.parse().context("adam_t")?;
    let layout = ModelLayout::new(&config.model_config(Aabb::new(min, max))?)
        .map_err(|e| anyhow::anyhow!("model: {e}"))?;
    // Parameters and both Adam moments, 4 bytes each, must all be in the file.
    let need = (layout.param_count() as u64).saturating_mul(12);
    if need > bytes.len() as u64 {
        bail!(
            "its configuration needs {need} bytes of parameters and Adam moments, the file \
             holds {}",
            bytes.len()
        );
    }
    let st = safetensors::SafeTensors::deserialize(bytes)?;
    let mut data = ModelData::new(layout, 0).map_err(|e| anyhow::anyhow!("{e}"))?;
    for g in Group::ALL {
        let i = g as usize;
        for (prefix, dst) in [
            ("params", &mut data.params[i]),
            ("adam_m", &mut data.m[i]),
            ("adam_v", &mut data.v[i]),
        ] {
            let name = format!("{prefix}.{}", g.name());
            let t = st.tensor(&name).with_context(|| format!("tensor {name}"))?;
            if t.dtype() != safetensors::Dtype::F32 || t.data().len() != 4 * dst.len() {
                bail!("tensor {name} has the wrong type or length for the configuration");
            }
            for (d, c) in dst.iter_mut().zip(t.data().as_chunks::<4>().0) {
                *d = f32::from_le_bytes(*c);
            }
        }
    }
    data.t = t;
    Ok((config, data, meta))
}
