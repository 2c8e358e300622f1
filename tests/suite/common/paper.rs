//! The paper's Table 4 and 5: the eight printed samples and the printed statistics.
#![allow(dead_code)]

/// Table 4: Euler angles `[Ax, Ay, Az]` (degrees) of the eight samples.
pub const TABLE_4: [[f64; 3]; 8] = [
    [-4.1106, 1.4515, 164.4249],
    [-4.1247, 1.5001, 164.4373],
    [-4.1231, 1.5011, 164.4326],
    [-4.1195, 1.5339, 164.4173],
    [-4.1043, 1.5008, 164.413],
    [-4.1294, 1.5051, 164.4842],
    [-4.106, 1.4553, 164.4531],
    [-4.1058, 1.4557, 164.4731],
];

/// Table 5: translations (mm) of the eight samples.
pub const TABLE_5: [[f64; 3]; 8] = [
    [-1282.9398, -2952.0529, 532.8236],
    [-1283.5764, -2951.5021, 531.9766],
    [-1283.5592, -2951.4957, 531.8821],
    [-1283.6027, -2951.4567, 531.3036],
    [-1283.6827, -2951.3879, 532.3849],
    [-1283.7936, -2952.4626, 531.8462],
    [-1282.7306, -2951.9466, 533.1364],
    [-1281.5911, -2955.1939, 534.1465],
];

/// Half a unit of the samples' last printed digit (they are printed with 4 decimals).
pub const SAMPLE_ROUNDING: f64 = 0.5e-4;

/// The printed statistics: `(section, statistic, printed values, allowance)`. The paper computed
/// its statistics from unrounded readings and printed the samples rounded, so a mean or rms of
/// the printed samples may differ by up to half a unit of the samples' precision (min and max
/// are samples themselves: no allowance). Of the 24, only the mean of Tz needs it: the printed
/// samples give 532.4374875, the paper prints 532.4374.
pub const PRINTED: [(&str, &str, [&str; 3], f64); 8] = [
    ("euler_deg", "min", ["-4.1294", "1.4515", "164.413"], 0.0),
    ("euler_deg", "max", ["-4.1043", "1.5339", "164.4842"], 0.0),
    (
        "euler_deg",
        "mean",
        ["-4.11543", "1.4879", "164.4419"],
        SAMPLE_ROUNDING,
    ),
    (
        "euler_deg",
        "rms",
        ["0.009256", "0.02812", "0.02430"],
        SAMPLE_ROUNDING,
    ),
    ("t_mm", "min", ["-1283.7936", "-2955.1939", "531.3036"], 0.0),
    ("t_mm", "max", ["-1281.5911", "-2951.3879", "534.1465"], 0.0),
    (
        "t_mm",
        "mean",
        ["-1283.1845", "-2952.1873", "532.4374"],
        SAMPLE_ROUNDING,
    ),
    (
        "t_mm",
        "rms",
        ["0.6976", "1.1891", "0.8454"],
        SAMPLE_ROUNDING,
    ),
];

/// Asserts every statistic of [`PRINTED`] as `got(section, stat)` gives it, within its
/// allowance.
pub fn assert_all_printed(got: impl Fn(&str, &str) -> [f64; 3]) {
    for (section, stat, printed, allowance) in PRINTED {
        let values = got(section, stat);
        for i in 0..3 {
            assert_printed(
                &format!("{section}.{stat}[{i}]"),
                values[i],
                printed[i],
                allowance,
            );
        }
    }
}

/// Asserts `got` agrees with `printed` (text, so its precision is known) to half a unit of its
/// last digit plus `allowance`.
pub fn assert_printed(label: &str, got: f64, printed: &str, allowance: f64) {
    let value: f64 = printed.parse().unwrap();
    let decimals = printed.split('.').nth(1).map_or(0, str::len) as i32;
    let half_unit = 0.5 * 10f64.powi(-decimals);
    assert!(
        (got - value).abs() <= half_unit + allowance + 1e-12,
        "{label} = {got} does not print as {printed}"
    );
}
