//! The TOML configuration, as far as `himap map` takes it before allocating the map: parse and
//! validate, build the mapper's and the model's configurations, size the map for its box.
#![no_main]
use himap::config::Config;
use himap_core::Aabb;
use libfuzzer_sys::fuzz_target;

fuzz_target!(|data: &[u8]| {
    let Ok(text) = std::str::from_utf8(data) else {
        return;
    };
    let Ok(cfg) = Config::from_toml(text) else {
        return;
    };
    let _ = cfg.mapper_config();
    let _ = cfg.adam_config();
    let aabb = match (cfg.scene.min, cfg.scene.max) {
        (Some(min), Some(max)) => Aabb::new(min, max),
        _ => Aabb::new([-2.0; 3], [2.0; 3]),
    };
    // Sizing only: nothing of the map's size is allocated here.
    let _ = himap::mapper_cli::map_bytes(&cfg, aabb, 2);
});
