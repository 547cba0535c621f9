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
    let mut bytes = safetensors::serialize(views, Some(meta))
        .with_context(|| format!("serialising {}", path.display()))?;
    canonical_header(&mut bytes);
    crate::atomic::write_bytes_atomic(path, &bytes)
}

/// Rewrites a serialised safetensors file's JSON header with its keys sorted, so that the
/// same map gives the same bytes (the crate takes the metadata as a `HashMap`, whose order
/// changes from run to run). The sorted header holds the same entries, so it has the same
/// length; where it would not (another JSON layout), the file is left as it is.
fn canonical_header(bytes: &mut [u8]) {
    let Some(len) = bytes
        .get(..8)
        .map(|b| u64::from_le_bytes(b.try_into().unwrap_or([0; 8])))
    else {
        return;
    };
    let Some(end) = usize::try_from(len).ok().and_then(|n| n.checked_add(8)) else {
        return;
    };
    let Some(header) = bytes.get_mut(8..end) else {
        return;
    };
    let text = String::from_utf8_lossy(header);
    let body = text.trim_end_matches(' ');
    // serde_json's `Value` keeps object keys in a BTreeMap: serialising it sorts them.
    let Ok(value) = serde_json::from_str::<serde_json::Value>(body) else {
        return;
    };
    let Ok(sorted) = serde_json::to_string(&value) else {
        return;
    };
    if sorted.len() == body.len() {
        header[..sorted.len()].copy_from_slice(sorted.as_bytes());
    }
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

#[cfg(test)]
mod tests {
    use super::*;

    /// The same map written twice gives the same bytes (the metadata's order is fixed), and
    /// the file reads back to the same configuration, box, step count and tensors.
    #[test]
    fn saving_the_same_map_twice_gives_the_same_bytes() {
        let mut config = crate::dump::tiny_map_config();
        config.model.geometry.cell_sizes = vec![0.64, 0.32];
        config.model.appearance.cell_sizes = vec![0.32];
        let aabb = Aabb::new([-1.0; 3], [1.0; 3]);
        let mut data = ModelData::new(
            ModelLayout::new(&config.model_config(aabb).unwrap()).unwrap(),
            3,
        )
        .unwrap();
        data.t = 17;
        let dir = std::env::temp_dir().join(format!("himap-persist-{}", std::process::id()));
        std::fs::create_dir_all(&dir).unwrap();
        let extra = [
            ("a", "1".to_string()),
            ("z", "2".to_string()),
            ("m", "3".to_string()),
        ];
        let mut files = Vec::new();
        for k in 0..4 {
            let path = dir.join(format!("map{k}.safetensors"));
            save_map_with(&path, &config, &data, &extra).unwrap();
            files.push(std::fs::read(&path).unwrap());
        }
        assert!(
            files.iter().all(|f| f == &files[0]),
            "the bytes differ between writes"
        );
        let (read_config, read, meta) = load_map_bytes(&files[0]).unwrap();
        assert_eq!(read_config.to_toml(), config.to_toml());
        assert_eq!(read.t, 17);
        assert_eq!(meta.get("m").map(String::as_str), Some("3"));
        for g in Group::ALL {
            let i = g as usize;
            assert_eq!(read.params[i], data.params[i]);
            assert_eq!(read.m[i], data.m[i]);
            assert_eq!(read.v[i], data.v[i]);
        }
        std::fs::remove_dir_all(&dir).ok();
    }
}
