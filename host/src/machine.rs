//! What a benchmark ran on: the processor's name and the vector extensions of the build.
//! Figures are only comparable on the same processor (on 2026-11-26 the same code took 1.4-2.8x
//! as long on an Intel Xeon as on the project's AMD EPYC, unevenly across stages), so
//! `loglio bench` and the criterion benches print both. No dependencies beyond std: the core's
//! benches include this file by path.

/// The processor the figures were measured on, as the OS names it: x86's `model name` in
/// `/proc/cpuinfo`; on ARM boards, which often have none, the device tree's model (a Jetson
/// says "NVIDIA Jetson AGX Orin ...") or the `Hardware` line. Figures are only comparable on
/// the same processor, so the report carries it.
pub fn cpu_model() -> Option<String> {
    let cpuinfo = std::fs::read_to_string("/proc/cpuinfo").unwrap_or_default();
    let dt = std::fs::read("/proc/device-tree/model").ok().map(|b| String::from_utf8_lossy(&b).into_owned());
    cpu_model_from(&cpuinfo, dt.as_deref())
}

fn cpu_model_from(cpuinfo: &str, device_tree_model: Option<&str>) -> Option<String> {
    let field = |name: &str| {
        cpuinfo.lines().find_map(|l| {
            let (k, v) = l.split_once(':')?;
            (k.trim() == name).then(|| v.trim().to_string()).filter(|v| !v.is_empty())
        })
    };
    let clean = |s: &str| {
        Some(s.trim_matches(|c: char| c == '\0' || c.is_whitespace()).to_string()).filter(|s| !s.is_empty())
    };
    field("model name").or_else(|| device_tree_model.and_then(clean)).or_else(|| field("Hardware"))
}

/// The vector extensions this build was compiled for (`.cargo/config.toml` builds x86-64 for
/// the building CPU): the same source runs 8 or 16 lanes per instruction depending on them.
pub fn vector_features() -> String {
    let built = [
        ("sse4.2", cfg!(target_feature = "sse4.2")),
        ("avx2", cfg!(target_feature = "avx2")),
        ("fma", cfg!(target_feature = "fma")),
        ("avx512f", cfg!(target_feature = "avx512f")),
        ("avx512bw", cfg!(target_feature = "avx512bw")),
        ("neon", cfg!(target_feature = "neon")),
    ];
    let f: Vec<&str> = built.iter().filter(|(_, on)| *on).map(|(name, _)| *name).collect();
    if f.is_empty() { "baseline".to_string() } else { f.join(" ") }
}

/// One line for a benchmark's log: `cpu: <model> (built for <extensions>)`.
pub fn describe() -> String {
    format!("cpu: {} (built for {})", cpu_model().as_deref().unwrap_or("unknown"), vector_features())
}

#[cfg(test)]
mod tests {
    // Paths through `super`, no `use`: the core's benches include this file, and there the
    // test functions are left out, so an import would be unused.

    #[test]
    fn cpu_model_is_read_from_x86_and_arm_descriptions() {
        let x86 = "processor\t: 0\nvendor_id\t: GenuineIntel\nmodel name\t: Intel(R) Xeon(R) Processor @ 2.50GHz\nflags\t\t: fpu\n";
        assert_eq!(super::cpu_model_from(x86, None).as_deref(), Some("Intel(R) Xeon(R) Processor @ 2.50GHz"));
        // An arm64 kernel lists no model name; the device tree names the board.
        let arm = "processor\t: 0\nBogoMIPS\t: 62.50\nCPU implementer\t: 0x41\nCPU part\t: 0xd42\n";
        assert_eq!(
            super::cpu_model_from(arm, Some("NVIDIA Jetson AGX Orin Developer Kit\0")).as_deref(),
            Some("NVIDIA Jetson AGX Orin Developer Kit")
        );
        assert_eq!(super::cpu_model_from("Hardware\t: BCM2835\n", None).as_deref(), Some("BCM2835"));
        // Empty values and a blank device tree fall through; nothing known is None, not "".
        assert_eq!(
            super::cpu_model_from("model name\t:   \nHardware\t: X\n", Some("\0")).as_deref(),
            Some("X")
        );
        assert_eq!(super::cpu_model_from("", None), None);
        assert!(!super::vector_features().is_empty());
        assert!(super::describe().starts_with("cpu: "));
    }
}
