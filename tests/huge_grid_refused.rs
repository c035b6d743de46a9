//! Grids whose tables a caller sizes are checked against the allocation limit (2³³ bytes)
//! before they are allocated: a hash grid of 64 levels × 8 features × 2²⁴ entries used to
//! ask for 26.6 GB, an `OccupancyGrid` of resolution 1290 for 10.7 GB (its 2³¹-cell cap
//! let it through), and networks of 2⁴⁰ layers aborted in the allocator.

use candle_core::{DType, Device};
use candle_nn::{VarBuilder, VarMap};
use neural_fields::encoding::{hash_grid, HashGridConfig};
use neural_fields::nn::{mlp, MlpConfig};
use neural_fields::volume::{GridConfig, OccupancyGrid};

fn message(e: neural_fields::Error) -> String {
    e.to_string()
}

#[test]
fn a_hash_table_past_the_limit_is_refused_naming_its_size() {
    let varmap = VarMap::new();
    let vb = VarBuilder::from_varmap(&varmap, DType::F32, &Device::Cpu);
    let config = HashGridConfig {
        levels: 64,
        features: 8,
        log2_table_size: 24,
        finest_resolution: 4096.0,
        ..HashGridConfig::default()
    };
    let e = message(hash_grid(&config, vb.pp("huge")).unwrap_err());
    assert!(
        e.starts_with("config.levels × config.features × table rows: "),
        "{e}"
    );
    assert!(e.contains("8589934592"), "the limit is stated: {e}");
    assert!(varmap.all_vars().is_empty(), "nothing was allocated");
    // 2⁴⁰ levels: refused by the lower bound before the levels are even listed.
    let config = HashGridConfig {
        levels: 1 << 40,
        ..HashGridConfig::default()
    };
    let e = message(hash_grid(&config, vb.pp("levels")).unwrap_err());
    assert!(e.starts_with("config.levels"), "{e}");
    // The default grid is still built.
    assert!(hash_grid(&HashGridConfig::default(), vb.pp("ok")).is_ok());
}

#[test]
fn an_occupancy_grid_past_the_limit_is_refused() {
    for resolution in [1290, 1200] {
        let e = OccupancyGrid::new(GridConfig {
            resolution,
            ..GridConfig::default()
        });
        let e = message(e.unwrap_err());
        assert!(e.starts_with("config.resolution: "), "{e}");
        assert!(e.contains("8589934592"), "{e}");
    }
    assert!(OccupancyGrid::new(GridConfig {
        resolution: 64,
        ..GridConfig::default()
    })
    .is_ok());
}

#[test]
fn a_network_of_too_many_layers_is_refused_before_its_layers_are_built() {
    let varmap = VarMap::new();
    let vb = VarBuilder::from_varmap(&varmap, DType::F32, &Device::Cpu);
    let config = MlpConfig {
        depth: 1 << 40,
        ..MlpConfig::default()
    };
    let e = message(mlp(&config, vb).unwrap_err());
    assert!(e.starts_with("config.depth: "), "{e}");
    assert!(varmap.all_vars().is_empty());
}
