// cast_test_fidelity: writes or checks the canonical cast.testing.RichEntry of
// the cross-language type-fidelity tests (tests/interop/test_cpp_fidelity.py).
// The value is rich_entry() of tests/interop/java_support.py (and the Java
// tests' canonical one): keep them in step.
//
// args: {"mode": "write", "id": ID, "variant": V}  adds the canonical value;
//       {"mode": "check", "id": ID, "variant": V}  reads ID and compares it
//       with the canonical value field by field; exit code 1 and the
//       differences on stdout if they differ. V (circle, name, polygon) picks
//       the member of the `shape` oneof.
// Prints one JSON line with the result, then stops.
#include <google/protobuf/util/message_differencer.h>

#include <cmath>
#include <iostream>
#include <limits>

#include "cast/cast.h"
#include "cast_fidelity.pb.h"
#include "probe_json.h"

namespace {

using cast::testing::RichEntry;

void point(RichEntry::Point* p, double x, double y, double z) {
  p->set_x(x);
  p->set_y(y);
  p->set_z(z);
}

// The same values as rich_entry(variant) in tests/interop/java_support.py and
// cast.itest.Rich.canonical in Java: one canonical value for every language.
RichEntry canonical(const std::string& variant) {
  using Limits64 = std::numeric_limits<std::int64_t>;
  RichEntry e;
  e.set_text(std::string("Gr\u00fc\u00dfe, \u4e16\u754c \u2014 \u2211 \U0001F680 ") + std::string(1, '\0') + " end");
  e.set_blob(std::string("\x00\xff\xfe\x80\x7f\x01", 6));
  e.set_int32_value(std::numeric_limits<std::int32_t>::min());
  e.set_int64_min(Limits64::min());
  e.set_int64_max(Limits64::max());
  e.set_uint32_value(std::numeric_limits<std::uint32_t>::max());
  e.set_uint64_max(std::numeric_limits<std::uint64_t>::max());
  e.set_sint64_value(-Limits64::max());
  e.set_fixed64_value(std::numeric_limits<std::uint64_t>::max() - 1);
  e.set_sfixed64_value(-1234567890123456789LL);
  e.set_double_value(3.141592653589793);
  e.set_double_tiny(5e-324);
  e.set_double_huge(1.7976931348623157e308);
  e.set_double_infinity(-std::numeric_limits<double>::infinity());
  e.set_float_value(0.1f);
  e.set_flag(true);
  e.set_colour(RichEntry::COLOUR_BLUE);
  e.set_shade(cast::testing::SHADE_DARK);
  point(e.mutable_origin(), 1.5, -2.25, 1e-10);

  auto* region = e.mutable_region();
  region->set_label("Z\u00fcrich");
  point(region->add_outline(), 0, 0, 0);
  point(region->add_outline(), 1, 0, 0);
  region->set_colour(RichEntry::COLOUR_GREEN);
  (*region->mutable_attributes())["\u043a\u043b\u044e\u0447"] = "\u0437\u043d\u0430\u0447\u0435\u043d\u0438\u0435";
  (*region->mutable_attributes())["a"] = "";
  auto* child = region->add_children();
  child->set_label("child");
  child->set_colour(RichEntry::COLOUR_RED);

  for (const char* tag : {"\u03b1", "", "tag"}) e.add_tags(tag);
  for (std::int64_t s : {Limits64::min(), std::int64_t{0}, Limits64::max(), std::int64_t{-1}}) e.add_samples(s);
  for (double w : {0.5, -0.0, 1e300}) e.add_weights(w);
  for (auto c : {RichEntry::COLOUR_RED, RichEntry::COLOUR_GREEN, RichEntry::COLOUR_BLUE, RichEntry::COLOUR_UNSPECIFIED}) {
    e.add_colours(c);
  }
  e.add_regions()->set_label("r1");
  auto* r2 = e.add_regions();
  r2->set_label("r2");
  (*r2->mutable_attributes())["k"] = "v";

  (*e.mutable_counts())["a"] = 1;
  (*e.mutable_counts())["negative"] = -5;
  (*e.mutable_counts())["max"] = Limits64::max();
  point(&(*e.mutable_points())[Limits64::min()], 1, 2, 3);
  (*e.mutable_points())[0];  // an empty message value
  point(&(*e.mutable_points())[42], -1, -1, -1);
  (*e.mutable_flags())[true] = "yes";
  (*e.mutable_flags())[false] = "no";
  e.set_maybe(0);  // present although 0: proto3 optional

  if (variant == "circle") {
    e.set_circle_radius(2.5);
  } else if (variant == "name") {
    e.set_shape_name("hexagon \u2b21");
  } else if (variant == "polygon") {
    auto* polygon = e.mutable_polygon();
    polygon->set_label("poly");
    point(polygon->add_outline(), 1, 1, 0);
  } else {
    throw cast::InvalidArgumentError("variant must be circle, name or polygon, not '" + variant + "'");
  }
  return e;
}

RichEntry::ShapeCase shapeOf(const std::string& variant) {
  if (variant == "circle") return RichEntry::kCircleRadius;
  if (variant == "name") return RichEntry::kShapeName;
  return RichEntry::kPolygon;
}

class Fidelity : public cast::UnmanagedComponent {
 public:
  void configure(const cast::Args& args) override {
    mode_ = args.getString("mode");
    id_ = args.getString("id");
    variant_ = args.getString("variant", "polygon");
    if ((mode_ != "write" && mode_ != "check") || id_.empty()) {
      throw cast::InvalidArgumentError("args must be {\"mode\": \"write\"|\"check\", \"id\": ID, \"variant\": V}");
    }
    canonical(variant_);  // an unknown variant fails here, before anything is written
  }

  void run() override {
    cast::probe::Object out;
    if (mode_ == "write") {
      auto r = add(id_, canonical(variant_));
      out.boolean("ok", true).str("written", id_).unum("revision", r.revision);
      std::cout << out.json() << std::endl;
      requestStop();
      return;
    }
    RichEntry got = get<RichEntry>(id_);
    std::string report;
    google::protobuf::util::MessageDifferencer differ;
    differ.ReportDifferencesToString(&report);
    bool equal = differ.Compare(canonical(variant_), got);
    // Presence is not part of MessageDifferencer's equality for every
    // version; check what proto3 optional and the oneof promise explicitly.
    if (!got.has_maybe()) {
      equal = false;
      report += "maybe: lost its presence\n";
    }
    if (got.has_never()) {
      equal = false;
      report += "never: present although never set\n";
    }
    if (got.shape_case() != shapeOf(variant_)) {
      equal = false;
      report += "shape: oneof case " + std::to_string(got.shape_case()) + ", not the " + variant_ + " member\n";
    }
    // -0.0 == 0.0 for the differencer; the sign must survive too.
    if (got.weights_size() != 3 || !std::signbit(got.weights(1))) {
      equal = false;
      report += "weights: -0.0 lost its sign\n";
    }
    out.boolean("ok", equal).str("checked", id_).str("differences", report).message("value", got);
    std::cout << out.json() << std::endl;
    requestStop();
    if (!equal) throw cast::InvalidArgumentError("RichEntry '" + id_ + "' differs from the canonical value:\n" + report);
  }

 private:
  std::string mode_;
  std::string id_;
  std::string variant_;
};

}  // namespace

CAST_COMPONENT_MAIN(Fidelity)
