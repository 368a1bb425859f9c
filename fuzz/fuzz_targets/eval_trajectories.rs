//! `loglio eval`'s inputs: two trajectories (TUM, or KITTI poses with or without a times file)
//! from the input, split at the first 0xff byte, evaluated with options from the first byte.
//! Bad files are errors; an evaluation that succeeds reports finite numbers (its JSON has no
//! `inf` or `NaN`).
#![no_main]
use libfuzzer_sys::fuzz_target;
use loglio_host::eval::{Alignment, DeltaUnit, EvalOptions, evaluate, parse_kitti, parse_tum};

fuzz_target!(|data: &[u8]| {
    let Some((&sel, rest)) = data.split_first() else { return };
    let cut = rest.iter().position(|&b| b == 0xff).unwrap_or(rest.len());
    let (a, b) = rest.split_at(cut);
    let b = b.get(1..).unwrap_or(&[]);
    let (Ok(a), Ok(b)) = (std::str::from_utf8(a), std::str::from_utf8(b)) else { return };
    let parse = |text: &str, name: &str| {
        if sel & 1 == 0 {
            parse_tum(text, name)
        } else {
            // KITTI: the poses, with the text after a blank line as its times file.
            match text.split_once("\n\n") {
                Some((poses, times)) if sel & 2 != 0 => parse_kitti(poses, name, Some((times, "times"))),
                _ => parse_kitti(text, name, None),
            }
        }
    };
    let (Ok(gt), Ok(est)) = (parse(a, "gt"), parse(b, "est")) else { return };
    let opt = EvalOptions {
        align: [Alignment::None, Alignment::Se3, Alignment::Sim3][usize::from(sel >> 2) % 3],
        max_diff: [0.01, 0.1, 1.0][usize::from(sel >> 4) % 3],
        offset: 0.0,
        rpe_delta: [1.0, 2.0, 0.5][usize::from(sel >> 6) % 3],
        rpe_unit: if sel & 0x40 == 0 { DeltaUnit::Frames } else { DeltaUnit::Metres },
        all_pairs: sel & 0x80 != 0,
        pairs_from_gt: sel & 0x20 != 0,
    };
    if let Ok(r) = evaluate(&gt, &est, &opt) {
        for s in [&r.ape_trans, &r.ape_rot_deg, &r.rpe_trans, &r.rpe_rot_deg] {
            let v = [s.rmse, s.mean, s.median, s.std, s.min, s.max, s.sse];
            assert!(v.iter().all(|x| x.is_finite()), "{s:?}");
        }
        let json = r.to_json();
        assert!(!json.contains("inf") && !json.contains("NaN"), "{json}");
    }
});
