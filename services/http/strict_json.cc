#include "services/http/strict_json.h"

#include <cctype>
#include <string>
#include <vector>

#include "absl/container/flat_hash_set.h"
#include "absl/functional/function_ref.h"
#include "absl/strings/numbers.h"
#include "absl/strings/str_cat.h"

namespace fleetmem::http {
namespace {

using google::protobuf::Descriptor;
using google::protobuf::EnumDescriptor;
using google::protobuf::FieldDescriptor;

// The field a JSON key names: its JSON name (lowerCamelCase) or its proto
// name, as the parser accepts either.
const FieldDescriptor* FindField(const Descriptor& type,
                                 const std::string& key) {
  for (int i = 0; i < type.field_count(); ++i) {
    const FieldDescriptor* field = type.field(i);
    if (field->json_name() == key || field->name() == key) return field;
  }
  return nullptr;
}

// A recursive-descent reader of JSON that checks each value against the
// field it fills. It stops quietly at malformed JSON (`malformed_`): the
// protobuf parser reports that.
class Checker {
 public:
  explicit Checker(std::string_view text) : text_(text) {}

  absl::Status CheckMessage(const Descriptor* type, const std::string& path) {
    SkipSpace();
    if (!Take('{')) return Malformed();
    absl::flat_hash_set<std::string> keys;
    SkipSpace();
    if (Take('}')) return absl::OkStatus();
    while (true) {
      SkipSpace();
      std::string key;
      if (!ReadString(&key)) return Malformed();
      if (!keys.insert(key).second) {
        return absl::InvalidArgumentError(
            absl::StrCat("request body: key \"", key, "\" appears twice in ",
                         path.empty() ? "the request" : path,
                         " (each field is given once)"));
      }
      SkipSpace();
      if (!Take(':')) return Malformed();
      const FieldDescriptor* field = nullptr;
      if (type != nullptr) field = FindField(*type, key);
      const std::string at = path.empty() ? key : absl::StrCat(path, ".", key);
      if (absl::Status value = CheckField(field, at); !value.ok()) {
        return value;
      }
      if (malformed_) return absl::OkStatus();
      SkipSpace();
      if (Take(',')) continue;
      if (Take('}')) return absl::OkStatus();
      return Malformed();
    }
  }

 private:
  // The value of `field` (null: unknown, or a type not checked here).
  absl::Status CheckField(const FieldDescriptor* field,
                          const std::string& path) {
    SkipSpace();
    if (field == nullptr || field->is_map()) return SkipValue();
    if (field->is_repeated() && Peek() == '[') {
      return CheckArray([&](int i) {
        const std::string element = absl::StrCat(path, "[", i, "]");
        if (Peek() == '[') {
          return absl::InvalidArgumentError(absl::StrCat(
              "request body: ", element, " is an array: ", path,
              " is a list of ",
              field->type() == FieldDescriptor::TYPE_MESSAGE ? "objects"
                                                             : "values",
              ", not of lists"));
        }
        return CheckSingle(field, element);
      });
    }
    return CheckSingle(field, path);
  }

  // One value of `field`'s type.
  absl::Status CheckSingle(const FieldDescriptor* field,
                           const std::string& path) {
    SkipSpace();
    if (field->type() == FieldDescriptor::TYPE_MESSAGE && Peek() == '{' &&
        field->message_type()->file()->package() != "google.protobuf") {
      return CheckMessage(field->message_type(), path);
    }
    if (field->type() == FieldDescriptor::TYPE_ENUM &&
        field->enum_type()->full_name() != "google.protobuf.NullValue") {
      return CheckEnum(field->enum_type(), path);
    }
    return SkipValue();
  }

  absl::Status CheckEnum(const EnumDescriptor* type, const std::string& path) {
    const size_t start = at_;
    std::string name;
    bool known = true;
    if (Peek() == '"') {
      if (!ReadString(&name)) return Malformed();
      known = type->FindValueByName(name) != nullptr;
    } else if (Peek() == '-' ||
               std::isdigit(static_cast<unsigned char>(Peek()))) {
      while (at_ < text_.size() &&
             (text_[at_] == '-' ||
              std::isdigit(static_cast<unsigned char>(text_[at_])))) {
        ++at_;
      }
      name = std::string(text_.substr(start, at_ - start));
      int number = 0;
      known = absl::SimpleAtoi(name, &number) &&
              type->FindValueByNumber(number) != nullptr;
    } else {
      return SkipValue();
    }
    if (known) return absl::OkStatus();
    std::string names;
    for (int i = 0; i < type->value_count(); ++i) {
      absl::StrAppend(&names, i == 0 ? "" : ", ", type->value(i)->name());
    }
    return absl::InvalidArgumentError(
        absl::StrCat("request body: ", path, ": ", name, " is not a value of ",
                     type->name(), " (one of ", names, ")"));
  }

  // An array at the cursor: `element(i)` checks its i-th value, the cursor
  // on it.
  absl::Status CheckArray(absl::FunctionRef<absl::Status(int)> element) {
    Take('[');
    SkipSpace();
    if (Take(']')) return absl::OkStatus();
    for (int i = 0;; ++i) {
      SkipSpace();
      if (absl::Status value = element(i); !value.ok()) return value;
      if (malformed_) return absl::OkStatus();
      SkipSpace();
      if (Take(',')) continue;
      if (Take(']')) return absl::OkStatus();
      return Malformed();
    }
  }

  // Any value, checked only for duplicate keys in its objects.
  absl::Status SkipValue() {
    SkipSpace();
    const char c = Peek();
    if (c == '{') return CheckMessage(nullptr, "an object");
    if (c == '[') return CheckArray([&](int) { return SkipValue(); });
    if (c == '"') {
      std::string ignored;
      return ReadString(&ignored) ? absl::OkStatus() : Malformed();
    }
    // A number, true, false or null.
    const size_t start = at_;
    while (at_ < text_.size() &&
           (std::isalnum(static_cast<unsigned char>(text_[at_])) ||
            text_[at_] == '-' || text_[at_] == '+' || text_[at_] == '.')) {
      ++at_;
    }
    return at_ > start ? absl::OkStatus() : Malformed();
  }

  // A string's text between its quotes, escapes kept as written (two
  // spellings of one key are not found equal; the parser keeps the last).
  bool ReadString(std::string* out) {
    if (!Take('"')) return false;
    while (at_ < text_.size()) {
      const char c = text_[at_++];
      if (c == '"') return true;
      if (c == '\\') {
        if (at_ >= text_.size()) return false;
        out->push_back(c);
        out->push_back(text_[at_++]);
        continue;
      }
      out->push_back(c);
    }
    return false;
  }

  absl::Status Malformed() {
    malformed_ = true;
    return absl::OkStatus();
  }
  char Peek() const { return at_ < text_.size() ? text_[at_] : '\0'; }
  bool Take(char c) {
    if (Peek() != c) return false;
    ++at_;
    return true;
  }
  void SkipSpace() {
    while (at_ < text_.size() &&
           std::isspace(static_cast<unsigned char>(text_[at_]))) {
      ++at_;
    }
  }

  std::string_view text_;
  size_t at_ = 0;
  bool malformed_ = false;
};

}  // namespace

absl::Status CheckStrictJson(std::string_view text, const Descriptor& type) {
  return Checker(text).CheckMessage(&type, "");
}

}  // namespace fleetmem::http
